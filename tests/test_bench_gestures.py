"""The JIGSAWS gesture benchmark's own bookkeeping (no training, no timing asserted): rows from several
runs accumulate, fold times come only from the model's own done markers, and the table puts pooled and
per-video figures in their columns and never calls a partial or low-edit run a target met."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import gestures_jigsaws as bench  # noqa: E402
from report_gestures import gestures_jigsaws_table  # noqa: E402


def _row(model: str, acc: float, edit: float, missing: list[int] | None = None) -> dict[str, Any]:
    pooled = {"accuracy": acc, "edit": edit, "f1@10": 91.0, "f1@25": 89.0, "f1@50": 80.0}
    per_video = {"accuracy": 0.5, "edit": 55.5, "f1@10": 66.6, "f1@25": 44.4, "f1@50": 22.2}
    return {"task": "knot_tying", "model": model, "epochs_option": None, "epochs": 100, "trained_in": model,
            "pooled": pooled, "per_video": per_video, "fold_mean": {"accuracy": acc, "edit": edit},
            "fold_sd": {"accuracy": 0.01, "edit": 1.0}, "missing_folds": missing or [], "n_folds": 2,
            "folds": [{"fold": 0, "user": "B", "accuracy": 0.7}, {"fold": 1, "user": "C", "accuracy": 0.9}],
            "timing": {"wall_s": 600.0, "jobs": 2}, "fold_seconds": {"0": 290.0, "1": 310.0}}


def _report(rows: list[dict[str, Any]]) -> dict[str, Any]:
    return {"tasks": {k: vars(v) for k, v in bench.TASKS.items()}, "target_edit": bench.TARGET_EDIT, "rows": rows}


def test_merge_replaces_only_the_same_task_model_and_epochs() -> None:
    old = [_row("mstcn", 0.7, 80.0), _row("transformer", 0.6, 70.0), {**_row("mstcn", 0.1, 1.0), "epochs_option": 1}]
    merged = bench.merge(old, [_row("mstcn", 0.8, 86.0)])
    assert sorted((r["model"], r["epochs_option"] or 0, r["pooled"]["accuracy"]) for r in merged) == [
        ("mstcn", 0, 0.8), ("mstcn", 1, 0.1), ("transformer", 0, 0.6)]


def test_fold_seconds_reads_the_models_done_markers_and_skips_broken_ones(tmp_path: Path) -> None:
    units = tmp_path / "jobs" / "units"
    markers = {"0": {"name": "mstcn fold 0 (louo B)", "seconds": 61.04}, "1": {"name": "mstcn fold 1 (louo C)"},
               "2": {"name": "baseline fold 0 (louo B)", "seconds": 5.0}, "3": "{not json",
               "4": {"name": "mstcn fold 3 (louo E)", "seconds": "soon"}, "5": {"name": "mstcn fold 5", "seconds": 7}}
    for unit, marker in markers.items():
        (units / unit).mkdir(parents=True)
        text = marker if isinstance(marker, str) else json.dumps(marker)
        (units / unit / "done.json").write_text(text, encoding="utf-8")
    assert bench.fold_seconds(tmp_path, "mstcn") == {0: 61.0, 5: 7.0}
    assert bench.fold_seconds(tmp_path, "baseline") == {0: 5.0}


def test_table_columns_and_target_verdicts() -> None:
    rows = [_row("mstcn", 0.81, 86.0), _row("transformer", 0.85, 84.9), _row("baseline", 0.9, 99.0, missing=[1])]
    lines = gestures_jigsaws_table(_report(rows))
    cells = {line.split(" | ")[0].lstrip("| "): line.strip("| ").split(" | ") for line in lines if line.startswith("| ")}
    header = cells["model"]
    mstcn = dict(zip(header, cells["MS-TCN++"]))
    assert (mstcn["acc"], mstcn["edit"], mstcn["F1@50"], mstcn["video acc"], mstcn["video edit"]) == (
        "81.0", "86.0", "80.0", "50.0", "55.5")
    assert cells["MS-TCN++"][-1] == "yes"
    assert cells["transformer"][-1] == "no"  # accuracy above the target, edit below 85
    assert cells["baseline (per-frame logistic regression)"][-1].startswith("—")  # a fold missing
    assert "B 70.0 C 90.0" in cells["MS-TCN++"] and "10.0 min, --jobs 2; a fold 4.8–5.2 min" in cells["MS-TCN++"]
    assert any("Needle Passing" in line for line in lines) and "Not measured yet." in lines


def test_causal_rows_coexist_with_the_offline_ones_and_show_the_accuracy_difference(tmp_path: Path) -> None:
    causal = {**_row("mstcn", 0.78, 84.0), "causal": True}
    merged = bench.merge([_row("mstcn", 0.81, 86.0), causal], [{**_row("mstcn", 0.77, 83.0), "causal": True}])
    assert sorted((bool(r.get("causal")), r["pooled"]["accuracy"]) for r in merged) == [(False, 0.81), (True, 0.77)]
    lines = gestures_jigsaws_table(_report(merged))
    titles = [line.split(" | ")[0].lstrip("| ") for line in lines if line.startswith("| ") and "MS-TCN" in line]
    assert titles == ["MS-TCN++", "MS-TCN++ (causal; acc -4.0 vs offline)"]  # offline first, then causal
    assert bench.run_dir(tmp_path, "knot_tying", "mstcn", None, causal=True).name == "mstcn-causal"
    assert bench.run_dir(tmp_path, "knot_tying", "mstcn", 3, causal=True).name == "mstcn-causal-e3"
    assert bench.run_dir(tmp_path, "knot_tying", "mstcn", None).name == "mstcn"


def test_a_learning_curve_pools_the_folds_at_the_epochs_every_fold_reached(tmp_path: Path) -> None:
    from report_gestures import curves_table

    def fold(k: int, points: dict[int, tuple[int, int, list[float]]]) -> None:
        history = [{"epoch": e, "loss": 1.0} for e in range(1, 21)]
        for e, (frames, correct, edit) in points.items():
            history[e - 1]["test_curve"] = {"frames": frames, "correct": correct, "edit": edit}
        (tmp_path / f"fold-{k}").mkdir()
        (tmp_path / f"fold-{k}" / "run.json").write_text(json.dumps({"history": history}), encoding="utf-8")

    assert bench.learning_curve(tmp_path) is None  # no run, or none scored: no curve
    fold(0, {10: (100, 50, [40.0]), 20: (100, 80, [70.0])})
    fold(1, {10: (300, 270, [80.0, 90.0]), 20: (300, 240, [60.0, 80.0])})
    fold(2, {})  # an older fold without --curve-every: left out, not counted
    curve = bench.learning_curve(tmp_path)
    assert curve == {"folds": 2, "epochs": [10, 20], "accuracy": [0.8, 0.8], "edit": [70.0, 70.0],
                     "by_fold": {"fold-0": {"10": [50, 100], "20": [80, 100]},
                                 "fold-1": {"10": [270, 300], "20": [240, 300]}}}
    fold(3, {10: (10, 10, [100.0])})  # a fold that has not reached epoch 20: only the epochs all folds have
    assert bench.learning_curve(tmp_path)["epochs"] == [10]
    lines = curves_table([{**_row("mstcn", 0.8, 70.0), "curve": curve}])
    assert "| epoch 10 | epoch 20 |" in lines[2] and "| 80.0 / 70.0 | 80.0 / 70.0 |" in lines[4]


def test_a_causal_row_finds_the_offline_run_of_the_same_inputs_and_compares_raw_curves() -> None:
    inputs = {"modalities": ["mtm", "psm"], "features": ["pos"], "sides": ["left", "right"]}
    offline = {**_row("mstcn", 0.80, 85.0), "variant": "ten", "train_args": "--model-rate 10",
               "inputs": {**inputs, "rate_hz": 10.0}, "curve": {"epochs": [50], "accuracy": [0.79], "edit": [70.0]}}
    causal = {**_row("mstcn", 0.72, 60.0), "causal": True, "inputs": {**inputs, "rate_hz": None},
              "curve": {"epochs": [50], "accuracy": [0.74], "edit": [60.0]}}
    lines = gestures_jigsaws_table(_report([offline, causal]))
    assert any("(causal; acc -5.0 vs offline, raw, epoch 50)" in line for line in lines)  # raw vs raw, not 72 vs 80
    other = {**causal, "inputs": {**inputs, "features": ["vel"], "rate_hz": None}}
    assert any("| MS-TCN++ (causal) |" in line for line in gestures_jigsaws_table(_report([offline, other])))


def test_a_delayed_causal_run_of_other_epochs_is_compared_at_every_epoch_both_curves_have() -> None:
    from report_gestures import causal_table

    offline = {**_row("transformer", 0.74, 65.0), "variant": "curve5", "train_args": "--curve-every 5",
               "curve": {"epochs": [10, 20, 30, 40], "accuracy": [0.772, 0.741, 0.744, 0.739], "edit": [70.0] * 4}}
    delayed = {**_row("transformer", 0.74, 66.0), "causal": True, "epochs_option": 30, "variant": "delay1s",
               "train_args": "--delay 1 --curve-every 5",
               "curve": {"epochs": [10, 20, 30], "accuracy": [0.749, 0.772, 0.740], "edit": [64.0] * 3}}
    lines = gestures_jigsaws_table(_report([offline, delayed]))
    assert any("(causal; acc -0.4 vs offline, raw, epoch 30)" in line for line in lines)
    table = causal_table([offline, delayed])
    assert "10: -2.3, 20: +3.1, 30: -0.4" in table[-2] and "delay1s" in table[-2] and "curve5" in table[-2]
    assert causal_table([offline]) == [] and causal_table([{**delayed, "curve": None}, offline]) == []


def test_an_unfinished_causal_run_is_compared_on_its_own_folds_only() -> None:
    """A causal run with folds B and C against an offline run of B, C, D: the difference is pooled over B
    and C (here 0), never the causal run's two easy folds against the offline run's three."""
    from report_gestures import causal_table, curve_deltas

    def curve(by_fold: dict[str, tuple[int, int]]) -> dict[str, Any]:
        correct, frames = sum(c for c, _ in by_fold.values()), sum(f for _, f in by_fold.values())
        return {"folds": len(by_fold), "epochs": [50], "accuracy": [correct / frames], "edit": [70.0],
                "by_fold": {g: {"50": [c, f]} for g, (c, f) in by_fold.items()}}

    offline = {**_row("mstcn", 0.6, 80.0), "variant": "all", "train_args": "", "curve": curve({"B": (90, 100), "C": (80, 100),
                                                                                "D": (10, 100)})}
    causal = {**_row("mstcn", 0.85, 80.0), "causal": True, "variant": "all", "train_args": "", "curve": curve({"B": (90, 100),
                                                                                              "C": (80, 100)})}
    assert curve_deltas(causal["curve"], offline["curve"]) == [(50, 0.0)]  # not +0.25 (85 % against 60 %)
    assert any("(causal; acc +0.0 vs offline, raw, epoch 50)" in line
               for line in gestures_jigsaws_table(_report([offline, causal])))
    assert "| B C |" in causal_table([offline, causal])[-2]
    elsewhere = {**causal, "curve": curve({"E": (99, 100)})}  # no fold in common: nothing to compare
    assert curve_deltas(elsewhere["curve"], offline["curve"]) == []
    old = {k: v for k, v in causal["curve"].items() if k != "by_fold"}  # a curve from before by_fold
    assert curve_deltas(old, {k: v for k, v in offline["curve"].items() if k != "by_fold"}) == []  # 2 vs 3 folds


def test_a_causal_run_with_other_training_options_is_compared_with_the_offline_run_trained_alike() -> None:
    """Causal MS-TCN++ with shifted inputs against offline MS-TCN++ with shifted inputs (-7.0 here), never
    against the offline run without the shift (-3.0), even where that one has the longer curve."""
    from report_gestures import causal_table

    def curve(points: dict[int, float]) -> dict[str, Any]:
        return {"folds": 1, "epochs": list(points), "accuracy": list(points.values()), "edit": [70.0] * len(points),
                "by_fold": {"B": {str(e): [round(a * 1000), 1000] for e, a in points.items()}}}

    plain = {**_row("mstcn", 0.74, 80.0), "variant": "curve10", "train_args": "--curve-every 10",
             "curve": curve({10: 0.72, 20: 0.74, 30: 0.75})}
    shifted = {**_row("mstcn", 0.78, 80.0), "variant": "shift", "train_args": "--augment-shift 1 --curve-every 10",
               "curve": curve({10: 0.76, 20: 0.78})}
    causal = {**_row("mstcn", 0.71, 60.0), "causal": True, "variant": "shift-delay1s",
              "train_args": "--augment-shift 1 --delay 1 --curve-every 10", "curve": curve({10: 0.70, 20: 0.71})}
    assert any("(causal; acc -7.0 vs offline, raw, epoch 20)" in line
               for line in gestures_jigsaws_table(_report([plain, shifted, causal])))
    assert "| MS-TCN++ [shift: `--augment-shift 1 --curve-every 10`] |" in causal_table([plain, shifted, causal])[-2]
    alone = gestures_jigsaws_table(_report([plain, causal]))  # no offline run trained alike: no difference shown
    assert any("| MS-TCN++ [shift-delay1s" in line and "vs offline" not in line for line in alone)



def test_resolved_training_settings_find_the_partner_after_a_default_changed(tmp_path: Path) -> None:
    """A causal run trained at a later default (``--delay 2`` alone, the shift now on by default) is compared
    with the offline run that trained with the shift (said explicitly then), not with the one whose
    ``--train-args`` read the same but trained before the default changed: rows carry the settings
    ``train gestures`` resolved (``training``, from the first finished fold's run.json)."""
    from gestures_jigsaws import training_settings
    from report_gestures import causal_table

    fold = tmp_path / "run" / "fold-0"
    fold.mkdir(parents=True)
    (fold / "run.json").write_text(json.dumps({"train_config": {"fold": 0, "device": "cpu", "epochs": 20,
                                                                "augment_shift": 1.0, "causal": True,
                                                                "delay_s": 2.0, "curve_every": 10}}))
    resolved = training_settings(tmp_path / "run")
    assert resolved == {"epochs": 20, "augment_shift": 1.0, "causal": True, "delay_s": 2.0, "curve_every": 10}
    assert training_settings(tmp_path / "nothing") is None

    def curve(points: dict[int, float]) -> dict[str, Any]:
        return {"folds": 1, "epochs": list(points), "accuracy": list(points.values()), "edit": [70.0] * len(points),
                "by_fold": {"B": {str(e): [round(a * 1000), 1000] for e, a in points.items()}}}

    before = {**_row("mstcn", 0.74, 80.0), "variant": "curve10", "train_args": "--curve-every 10",
              "curve": curve({10: 0.72, 20: 0.74}),
              "training": {"epochs": 100, "augment_shift": 0.0, "causal": False, "delay_s": 0.0, "curve_every": 10}}
    shifted = {**_row("mstcn", 0.78, 80.0), "variant": "shift", "train_args": "--augment-shift 1 --curve-every 10",
               "curve": curve({10: 0.76, 20: 0.78}),
               "training": {"epochs": 20, "augment_shift": 1.0, "causal": False, "delay_s": 0.0, "curve_every": 10}}
    causal = {**_row("mstcn", 0.73, 60.0), "causal": True, "variant": "delay2s",
              "train_args": "--delay 2 --curve-every 10", "curve": curve({10: 0.72, 20: 0.73}), "training": resolved}
    assert any("(causal; acc -5.0 vs offline, raw, epoch 20)" in line
               for line in gestures_jigsaws_table(_report([before, shifted, causal])))
    assert "| MS-TCN++ [shift: `--augment-shift 1 --curve-every 10`] |" in causal_table([before, shifted, causal])[-2]
    untold = {**causal, "training": None}  # a row without them: matched by its --train-args, as before
    assert any("(causal; acc -1.0 vs offline, raw, epoch 20)" in line
               for line in gestures_jigsaws_table(_report([before, shifted, untold])))
