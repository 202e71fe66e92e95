"""Training runs: a tiny configuration trains on CPU, is deterministic, and its folder describes it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers.cli import midas
from helpers.gesture_sessions import write_gesture_dataset
from midas_cli.errors import ConfigError
from midas_cli.models.ablation import GridRow, parse_grid
from midas_cli.models.data import DatasetConfig
from midas_cli.models.splits import instances
from midas_cli.models.train import TrainConfig, evaluate_checkpoint, shuffled_instance_labels, train_run

TINY_MSTCN = {"pg_layers": 4, "refinement_stages": 1, "refinement_layers": 4, "feature_maps": 16}


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> list[Path]:
    return write_gesture_dataset(tmp_path_factory.mktemp("train"), n_trials=4, subjects=2, n_frames=300)


def tiny_run(sessions, out: Path, **overrides):
    config = TrainConfig(**{"model": "mstcn", "epochs": 3, "seed": 5, "lr": 5e-3, "model_options": TINY_MSTCN,
                            **overrides})
    return train_run(sessions, DatasetConfig(("emht",), ("pos", "vel")), config, out)


def test_tiny_run_learns_and_writes_a_self_describing_folder(sessions, tmp_path):
    result = tiny_run(sessions, tmp_path / "run")
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["split"]["kind"] == "gesture" and run["split"]["seed"] == 5 and run["split"]["test"]
    assert len(run["data_fingerprint"]) == 64 and run["code"]["models_sha256"]
    assert run["model_config"]["feature_maps"] == 16 and len(run["history"]) == 3
    assert run["history"][-1]["loss"] < run["history"][0]["loss"]
    saved = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    assert saved["classes"] == ["G1", "G2", "G3", "G4"] and "state_dict" in saved
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["test"]["summary"]["frames"] > 0 and len(metrics["test"]["confusion"]) == 4
    assert result.metrics["test"]["summary"]["accuracy"] > 0.4  # 4 classes: chance is 0.25
    assert (tmp_path / "run" / "plots" / "confusion.png").stat().st_size > 0
    assert list((tmp_path / "run" / "predictions").glob("*.csv"))
    # metrics.json says "finished": cross-validation pools the folds' predictions as soon as every fold has
    # it (on a cluster, while other folds are still writing), so it must be the run's last file
    finished = (tmp_path / "run" / "metrics.json").stat().st_mtime_ns
    assert all(p.stat().st_mtime_ns <= finished for p in (tmp_path / "run").rglob("*") if p.is_file())


def test_same_seed_same_run_and_eval_only_reproduces(sessions, tmp_path):
    first = tiny_run(sessions, tmp_path / "a", epochs=2)
    second = tiny_run(sessions, tmp_path / "b", epochs=2)
    assert first.metrics["test"] == second.metrics["test"]
    a = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)["state_dict"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    again = evaluate_checkpoint(sessions, tmp_path / "a" / "checkpoint.pt", tmp_path / "eval")
    assert again.metrics["test"]["summary"] == first.metrics["test"]["summary"]
    with pytest.raises(ConfigError, match="already holds a run"):
        tiny_run(sessions, tmp_path / "a")


def test_a_learning_curve_scores_the_test_split_without_changing_the_training(sessions, tmp_path):
    plain = tiny_run(sessions, tmp_path / "plain", epochs=3)
    curved = tiny_run(sessions, tmp_path / "curved", epochs=3, curve_every=2)
    a = torch.load(tmp_path / "plain" / "checkpoint.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / "curved" / "checkpoint.pt", weights_only=True)["state_dict"]
    assert all(torch.equal(a[k], b[k]) for k in a)  # the same weights: scoring draws no random numbers
    assert curved.metrics["test"] == plain.metrics["test"]
    history = json.loads((tmp_path / "curved" / "run.json").read_text())["history"]
    assert [e["epoch"] for e in history if "test_curve" in e] == [2, 3]  # every 2nd epoch and the last
    last = history[-1]["test_curve"]
    summary = curved.metrics["test"]["raw"]["summary"] if "raw" in curved.metrics["test"] else curved.metrics["test"]["summary"]
    assert last["frames"] == summary["frames"] and last["correct"] / last["frames"] == pytest.approx(summary["accuracy"])
    assert len(last["edit"]) == len(json.loads((tmp_path / "curved" / "run.json").read_text())["split"]["test"])
    with pytest.raises(ConfigError, match="curve-every"):
        TrainConfig(curve_every=-1)


def test_shuffled_instance_labels_keep_structure_but_break_the_mapping():
    y = [np.array([0, 0, 1, 1, 1, 2, -1, 3, 3]), np.array([1, 1, 0, 0, 2, 2, 3])]
    shuffled = shuffled_instance_labels(y, seed=0)
    for before, after in zip(y, shuffled):
        assert ((before == -1) == (after == -1)).all()
        runs = np.flatnonzero(np.diff(before)) + 1
        for segment in np.split(after, runs):
            assert len(set(segment.tolist())) == 1  # each instance still has one class
    found = [(i, cls, a) for i, y_i in enumerate(y) for cls, a, _ in instances(y_i)]
    after = sorted(int(shuffled[i][a]) for i, _, a in found)
    assert after == sorted(cls for _, cls, _ in found)  # the same instance classes, dealt to other instances
    assert any((a != b).any() for a, b in zip(y, shuffled))


def test_grid_rows_parse_and_title_like_the_paper():
    rows = parse_grid("emht:pos,ori,vel:exclude-clutch;emht:pos,ori,vel;mtm:pos,ori:exclude-clutch;emht+image:pos,vel")
    assert rows[0] == GridRow(("emht",), ("pos", "ori", "vel"), True)
    assert [r.modality_title() for r in rows] == ["EmHT", "EmHT-NC", "MTM-NG", "EmHT, Image-NC"]
    assert rows[3].feature_title() == "pos., vel., RGB"
    assert len(parse_grid(None)) == 14
    with pytest.raises(ConfigError):
        parse_grid("emht")


@pytest.mark.slow
def test_cli_train_eval_only_and_ablation(sessions, tmp_path):
    root = str(sessions[0].parent)
    run = midas("train", "gestures", root, "--model", "transformer", "--epochs", "1", "--seed", "1",
                "--accelerator", "cpu", "--out", str(tmp_path / "run"), "--json", check=True)
    summary = json.loads(run.stdout)["test"]
    assert 0.0 <= summary["accuracy"] <= 1.0 and "f1@50" in summary
    assert "epochs" in run.stderr  # progress bar on stderr
    again = midas("train", "gestures", root, "--eval-only", str(tmp_path / "run" / "checkpoint.pt"),
                  "--device", "cpu", "--out", str(tmp_path / "eval"), "--json", check=True)  # the old name
    assert json.loads(again.stdout)["test"] == summary
    assert "midas: warning: --device is now --accelerator" in again.stderr
    table = midas("train", "ablation", root, "--models", "transformer", "--epochs", "1",
                  "--grid", "emht:pos:exclude-clutch;psm:pos", "--out", str(tmp_path / "abl"), check=True)
    assert "| MTRSAP | EmHT | pos. |" in table.stdout and "Skipped" in table.stdout  # no PSM stream
    assert (tmp_path / "abl" / "table.tex").read_text().count("\\\\") >= 2
    assert (tmp_path / "abl" / "table.csv").read_text().splitlines()[0].startswith("Dataset,Model,Modality")
    bad = midas("train", "gestures", root, "--model", "lstm", "--out", str(tmp_path / "x"))
    assert bad.returncode == 2 and "lstm" in bad.stderr


def test_cli_skips_unlabelled_sessions_with_a_note_and_fails_only_when_none_remain(tmp_path):
    found = write_gesture_dataset(tmp_path / "data", n_trials=3, subjects=1, n_frames=240)
    unlabelled = found[1]
    (unlabelled / "labels" / "gestures.csv").unlink()  # a trial nobody annotated
    run = midas("train", "gestures", str(tmp_path / "data"), "--model", "transformer", "--epochs", "1",
                "--split", "loto", "--out", str(tmp_path / "run"), "--json", check=True)
    assert "1 of 3 sessions skipped" in run.stderr and unlabelled.name in run.stderr
    saved = json.loads((tmp_path / "run" / "run.json").read_text())
    assert list(saved["skipped_sessions"]) == [str(unlabelled)]
    assert unlabelled.name not in {t["name"] for t in saved["trials"]} and len(saved["trials"]) == 2
    summary = json.loads(run.stdout)["test"]
    assert summary["frames_all"] >= summary["frames"] > 0 and "accuracy_with_background" in summary
    for session in found:
        (session / "labels" / "gestures.csv").unlink(missing_ok=True)
    none = midas("train", "gestures", str(tmp_path / "data"), "--model", "mstcn", "--epochs", "1", "--out", str(tmp_path / "x"))
    assert none.returncode == 4 and "none of the 3 sessions has label set 'gestures'" in none.stderr
    assert not (tmp_path / "x").exists()  # refused: no empty run folder left behind
    (tmp_path / "mine").mkdir()
    again = midas("train", "gestures", str(tmp_path / "data"), "--model", "mstcn", "--epochs", "1", "--out", str(tmp_path / "mine"))
    assert again.returncode == 4 and (tmp_path / "mine").is_dir()  # a folder the user made is theirs: kept
