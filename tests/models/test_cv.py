"""Cross-validation (issue 19 item 1) and the per-frame baseline (item 4): JIGSAWS protocols on a tiny
JIGSAWS-like folder (users B, C, D; trials 1, 2), cv.json / cv.md, fold folders, ablation with CV."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from helpers.cli import midas
from helpers.gesture_sessions import write_gesture_session
from midas_cli.models import cv
from midas_cli.models.data import DatasetConfig, build_dataset
from midas_cli.models.splits import fold_groups, make_split
from midas_cli.models.train import TrainConfig, train_run

USERS, TRIALS = ("B", "C", "D"), (1, 2)
METRICS = ("accuracy", "edit", "f1@10", "f1@25", "f1@50")


@pytest.fixture(scope="module")
def jigsaws(tmp_path_factory) -> Path:
    """Sessions as `midas import jigsaws` names them: subject = the user letter, trial = the number."""
    root = tmp_path_factory.mktemp("cv") / "data"
    for i, (user, trial) in enumerate((u, t) for u in USERS for t in TRIALS):
        write_gesture_session(root, user, trial, n_frames=180, seed=i)
    return root


@pytest.fixture(scope="module")
def dataset(jigsaws):
    return build_dataset(sorted(p for p in jigsaws.iterdir() if p.is_dir()), DatasetConfig(("emht",), ("pos",)))


def test_louo_trains_on_every_other_user_and_loso_holds_out_one_trial_of_every_user(dataset):
    by_name = {t.name: t for t in dataset.trials}
    assert fold_groups(dataset, "louo") == list(USERS)
    for k, user in enumerate(USERS):
        split = make_split(dataset, "louo", seed=0, fold=k)
        assert {by_name[n].subject for n, _, _ in split.units["test"]} == {user}
        train = {n for n, _, _ in split.units["train"]}
        assert train == {t.name for t in dataset.trials if t.subject != user}  # no user lost to validation
        assert not split.units["val"] and split.validation == "none (fixed epochs)" and split.group == user
    assert fold_groups(dataset, "loso") == ["1", "2"]
    for k, trial in enumerate(TRIALS):
        split = make_split(dataset, "loso", seed=0, fold=k)
        test = [by_name[n] for n, _, _ in split.units["test"]]
        assert sorted(t.subject for t in test) == list(USERS) and {t.trial for t in test} == {trial}
        assert {by_name[n].trial for n, _, _ in split.units["train"]} == set(TRIALS) - {trial}
    inner = make_split(dataset, "louo", seed=3, fold=0, validation="inner")
    val, train = {u[0] for u in inner.units["val"]}, {u[0] for u in inner.units["train"]}
    assert len(val) == 1 and not val & train and {by_name[n].subject for n in val} <= {"C", "D"}
    assert val | train == {t.name for t in dataset.trials if t.subject != "B"} and inner.validation.startswith("inner")
    assert make_split(dataset, "louo", seed=3, fold=0, validation="inner").to_json() == inner.to_json()


def test_baseline_learns_an_easy_problem(jigsaws, tmp_path):
    sessions = sorted(p for p in jigsaws.iterdir() if p.is_dir())
    config = TrainConfig(model="baseline", split="louo", fold=0, epochs=25, seed=1)
    result = train_run(sessions, DatasetConfig(("emht",), ("ori",)), config, tmp_path / "run")
    assert result.metrics["test"]["summary"]["accuracy"] > 0.6  # 4 classes: chance 0.25
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["train_config"]["validation"] == "none" and run["split"]["validation"] == "none (fixed epochs)"


def test_cli_louo_fold_all_writes_cv_json_md_and_fold_folders(jigsaws, tmp_path):
    out = tmp_path / "louo"
    result = midas("train", "gestures", str(jigsaws), "--model", "baseline-mlp", "--modalities", "emht",
                   "--features", "pos", "--split", "louo", "--fold", "all", "--epochs", "1", "--out", str(out),
                   "--json", check=True)
    printed = json.loads(result.stdout)
    report = json.loads((out / "cv.json").read_text())
    assert printed["pooled"] == report["pooled"] and report["protocol"] == "louo"
    assert report["validation"] == "none (fixed epochs)" and report["groups"] == list(USERS)
    assert [f["group"] for f in report["folds"]] == list(USERS) and report["missing_folds"] == []
    for fold in report["folds"]:
        assert len(fold["test_trials"]) == 2 and len(fold["train_trials"]) == 4 and not fold["val_trials"]
        assert all(0 <= fold[m] <= (1 if m == "accuracy" else 100) for m in METRICS)
    for part in (report, report["baseline"]):
        assert all(m in part["mean"] and m in part["sd"] and m in part["pooled"] for m in METRICS)
    assert report["baseline"]["model"] == "baseline" and report["pooled"]["sequences"] == 6
    for k in range(3):
        assert (out / f"fold-{k}" / "metrics.json").is_file() and (out / "baseline" / f"fold-{k}" / "run.json").is_file()
    table = (out / "cv.md").read_text()
    assert table.count("| Baseline (MLP) | ") == 6 and "| Baseline (MLP) | mean ± sd |" in table
    assert "| Baseline (MLP) | per video |" in table and report["per_video"]["videos"] == 6
    assert "| Baseline (MLP) | pooled |" in table and "| Baseline (MLP) | 2 | D |" in table
    assert "Clean-up: decoded with the training split's gesture order, weight 30, segments at least --min-segment auto" in table
    assert "| Baseline (LR) | mean ± sd |" in table and "none (fixed epochs)" in table
    # folds run elsewhere: cv-summary aggregates what exists and names what is missing
    partial = tmp_path / "partial"
    shutil.copytree(out / "fold-0", partial / "fold-0")
    again = midas("train", "cv-summary", str(partial), "--json", check=True)
    assert json.loads((partial / "cv.json").read_text())["missing_folds"] == [1, 2] and "not finished" in again.stderr
    assert cv.summarise(out)["mean"] == printed["mean"]


def test_cli_ablation_cross_validates_with_a_baseline_row(jigsaws, tmp_path):
    out = tmp_path / "abl"
    table = midas("train", "ablation", str(jigsaws), "--models", "baseline-mlp", "--grid", "emht:pos",
                  "--split", "loso", "--fold", "all", "--epochs", "1", "--out", str(out), check=True).stdout
    assert "| Baseline (MLP) |" in table and "| Baseline (LR) |" in table and " ± " in table and "F1@50" in table
    for model in ("baseline-mlp", "baseline"):
        report = json.loads((out / "runs" / f"{model}__emht__pos" / "cv.json").read_text())
        assert report["protocol"] == "loso" and [f["group"] for f in report["folds"]] == ["1", "2"]
    assert json.loads((out / "ablation.json").read_text())["results"][0]["folds"] == 2


def test_single_fold_into_fold_folder_aggregates_when_the_last_one_finishes(jigsaws, tmp_path):
    sessions = sorted(p for p in jigsaws.iterdir() if p.is_dir())
    data = DatasetConfig(("emht",), ("pos",))
    for k in (0, 1):
        assert not (tmp_path / "cv.json").exists()
        cv.run_fold(sessions, data, TrainConfig(model="baseline", split="loso", fold=k, epochs=1), cv.fold_dir(tmp_path, k))
    assert cv.complete(tmp_path)
    report = cv.summarise(tmp_path)
    assert len(report["folds"]) == 2 and report["sd"]["accuracy"] is not None


def test_pooled_and_per_video_f1_are_both_reported_and_differ_as_defined():
    """Pooled F1@k sums TP/FP/FN over videos (MS-TCN); per video averages each video's own F1@k."""
    from midas_cli.models import metrics as M

    long_right = np.repeat([0, 1, 2, 3], 50)  # 4 segments, all found
    short_truth = np.array([0, 0, 1, 1])
    short_wrong = np.array([2, 2, 3, 3])  # 2 segments, none found
    preds, truths = [long_right, short_wrong], [long_right, short_truth]
    per_video = cv.per_video_means(preds, truths)
    pooled = M.evaluate(preds, truths, ["a", "b", "c", "d"])["summary"]
    assert per_video["f1@50"] == pytest.approx(50.0)  # (100 + 0) / 2
    assert pooled["f1@50"] == pytest.approx(100 * 2 * 4 / (2 * 4 + 2 + 2))  # TP 4, FP 2, FN 2 summed
    assert per_video["accuracy"] == pytest.approx(0.5) and per_video["videos"] == 2
