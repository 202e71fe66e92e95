"""`midas eval correlation|pedals` and `calibrate fps-optimize` on synthetic sessions with known truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from midas_cli.analysis.align import align_and_write
from midas_cli.analysis.eval_runs import best_rule
from midas_cli.analysis.evaluation import PedalRule, correlation_table
from midas_cli.session.derived import read_aligned
from helpers.analysis_sessions import raven_session
from helpers.cli import midas


@pytest.fixture(scope="module")
def aligned(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("eval")
    session = raven_session(root, duration_s=30.0, fps_delay_ms=100.0)
    align_and_write(session)
    return session


def test_pedals_against_robot_clutch_measure_the_injected_delay(aligned: Path, tmp_path: Path) -> None:
    result = midas("eval", "pedals", str(aligned), "--out", str(tmp_path), "--json", check=True)
    rows = {r["pedal"]: r for r in json.loads(result.stdout)["tables"]["pedals"]}
    clutch = rows["clutch"]
    assert clutch["lag_ms"] == pytest.approx(100.0, abs=1000 / 30)  # FPS states delayed by 100 ms
    assert 0.5 < clutch["f1"] < 1.0 and clutch["recall"] < 1.0
    for ext in ("csv", "tex"):
        assert (tmp_path / f"pedals.{ext}").is_file()
    assert "simulated" in (tmp_path / "pedals.md").read_text()
    assert (aligned / "derived" / "plots" / "pedal_clutch.png").stat().st_size > 1000


def test_pedal_ground_truth_file_is_used_per_pedal(aligned: Path, tmp_path: Path) -> None:
    table = read_aligned(aligned)
    clutch = table.column("fps.ch5_pressed")  # a ground truth identical to the detection
    gt = pd.DataFrame({"frame": table.frame, "t_host_ns": table.t_host_ns, "clutch": np.nan_to_num(clutch).astype(int),
                       "camera": 0})
    gt.to_csv(aligned / "derived" / "pedals_gt.csv", index=False)
    try:
        result = midas("eval", "pedals", str(aligned), "--out", str(tmp_path), "--no-plots", "--json", check=True)
    finally:
        (aligned / "derived" / "pedals_gt.csv").unlink()
    rows = {r["pedal"]: r for r in json.loads(result.stdout)["tables"]["pedals"]}
    assert rows["clutch"]["f1"] == pytest.approx(1.0) and rows["clutch"]["lag_ms"] == 0.0
    assert rows["camera"]["recall"] is None  # no ground-truth presses: undefined, not 0


def test_best_rule_finds_threshold_and_polarity() -> None:
    volts = np.array([0.1, 0.2, 3.0, 3.5, 0.3, 2.9, 0.2])
    truth = np.array([0, 0, 1, 1, 0, 1, 0])
    rule, f1 = best_rule(volts, truth)
    assert (rule.polarity, rule.threshold_v, f1) == ("above", 2.9, 1.0)
    rule, f1 = best_rule(-volts, truth)  # an inverted divider: pressed = low voltage
    assert rule.polarity == "below" and f1 == 1.0
    assert PedalRule(1.0, "below").apply(np.array([0.5, 2.0, np.nan]))[:2].tolist() == [1.0, 0.0]


def test_correlation_tables_and_files(aligned: Path, tmp_path: Path) -> None:
    midas("calibrate", "emht", str(aligned), "--target", "mtm", "--rigid-only", check=True)
    align_and_write(aligned)
    result = midas("eval", "correlation", str(aligned), "--out", str(tmp_path), "--json", check=True)
    tables = json.loads(result.stdout)["tables"]
    emht = {r["comparison"]: r for r in tables["correlation"]}["EmHT-MTM"]
    assert emht["model"] == "rigid"
    assert min(emht["X CoS"], emht["Y CoS"], emht["Z CoS"]) >= 0.9
    assert emht["X NRMSE"] < 5.0
    assert {r["comparison"] for r in tables["grasper"]} >= {"PSM-MTM", "EmHT-MTM"}
    lag = {r["comparison"]: r["lag_ms"] for r in tables["lag"]}
    assert lag["EmHT-MTM"] == pytest.approx(40.0, abs=1000 / 30)
    assert (tmp_path / "correlation.tex").read_text().startswith("\\begin{table}")
    assert (aligned / "derived" / "plots" / "trajectory_emht_left.png").is_file()
    assert (aligned / "derived" / "plots" / "trajectory_emht_right.png").is_file()


def test_correlation_table_prefers_mlp_and_averages_sessions() -> None:
    rows = [{"session": s, "comparison": "EmHT-MTM", "model": m, "subset": "all", "hand": "left", "axis": "X",
             "cos": c, "nrmse": 10.0, "frames": 5} for s, m, c in (("a", "rigid", 0.1), ("a", "mlp", 0.8),
                                                                     ("b", "mlp", 0.6))]
    table = correlation_table(rows)
    assert table["model"].tolist() == ["mlp"] and table["X CoS"].iloc[0] == pytest.approx(0.7)
    assert table["n"].iloc[0] == 2


def test_correlation_table_uses_the_selected_model_and_marks_a_worse_mlp() -> None:
    from midas_cli.analysis.evaluation import mark_worse

    rows = [{"session": "a", "comparison": "HandKP-MTM", "model": m, "subset": "all", "hand": "left", "axis": "X",
             "cos": c, "nrmse": 10.0, "frames": 5, "selected": m == "rigid"} for m, c in (("rigid", 0.9), ("mlp", 0.0))]
    table = correlation_table(rows)
    assert table["model"].tolist() == ["rigid"] and table["X CoS"].iloc[0] == pytest.approx(0.9)
    worse = {"HandKP-MTM": {"mlp_worse_than_rigid": True}}
    marked = mark_worse(pd.DataFrame({"model": ["rigid", "mlp"]}), worse, "HandKP-MTM")
    assert marked["model"].tolist() == ["rigid", "mlp*"]
    assert mark_worse(pd.DataFrame({"model": ["mlp"]}), worse, "EmHT-MTM")["model"].tolist() == ["mlp"]


def test_eval_pedals_uses_the_thresholds_fps_optimize_found(aligned: Path, tmp_path: Path) -> None:
    """`calibrate fps-optimize` writes calib/fps_optimized.json; `eval pedals --optimized` reads it back."""
    midas("calibrate", "fps-optimize", str(aligned), check=True)
    try:
        rules = json.loads((aligned / "calib" / "fps_optimized.json").read_text())["pedals"]
        result = midas("eval", "pedals", str(aligned), "--optimized", "--out", str(tmp_path), "--no-plots", "--json",
                       check=True)
    finally:
        (aligned / "calib" / "fps_optimized.json").unlink()
    assert "clutch" in rules and rules["clutch"]["polarity"] in ("above", "below")
    rows = {r["pedal"]: r for r in json.loads(result.stdout)["tables"]["pedals"]}
    assert 0.5 < rows["clutch"]["f1"] <= 1.0
