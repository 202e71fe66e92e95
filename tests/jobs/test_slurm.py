"""`--executor slurm` on a real one-node SLURM (tests/helpers/slurm_fixture.py), against local runs: the
same aligned values and cross-validation metrics, failed units reported with their log and error line
while the others' results stay, re-runs skipping the units done (issue 16)."""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from helpers.analysis_sessions import raven_session
from helpers.cli import midas
from helpers.gesture_sessions import write_gesture_session
from midas_cli.session.derived import read_aligned

pytestmark = [pytest.mark.slurm, pytest.mark.slow]  # a real one-node cluster: long checks (make test-slow)
WAIT_S = 300  # a loaded CI machine is slow; nothing here assumes speed


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("slurm-sessions")
    return [raven_session(root, trial=k, duration_s=3.0, seed=k) for k in range(1, 9)]


def copies(sessions: list[Path], dest: Path) -> list[Path]:
    return [Path(shutil.copytree(s, dest / s.name)) for s in sessions]


def slurm_env(slurm, tmp_path: Path) -> dict[str, str]:
    config = tmp_path / "config.toml"
    config.write_text('[slurm]\npartition = "debug"\nmem = "500M"\n', encoding="utf-8")
    return {**slurm.env, "MIDAS_CONFIG": str(config), "MIDAS_PROGRESS_INTERVAL_S": "0"}


def aligned(session: Path) -> tuple[list[str], np.ndarray]:
    table = read_aligned(session)
    return list(table.columns), table.values


def test_align_on_slurm_matches_local_and_a_rerun_skips_done_sessions(slurm, sessions, tmp_path):
    local = copies(sessions, tmp_path / "local")
    remote = copies(sessions, tmp_path / "remote")
    midas("align", *map(str, local), "--jobs", "2", check=True, timeout=WAIT_S)
    run = tmp_path / "run"
    env = slurm_env(slurm, tmp_path)
    result = midas("align", *map(str, remote), "--executor", "slurm", "--run-dir", str(run), "--slurm-time",
                   "00:10:00", "--json", env=env, timeout=WAIT_S)
    assert result.returncode == 0, result.stderr + slurm.log_tail()
    assert [Path(r["session"]).name for r in json.loads(result.stdout)] == [s.name for s in sessions]
    for a, b in zip(local, remote):
        (cols_a, values_a), (cols_b, values_b) = aligned(a), aligned(b)
        assert cols_a == cols_b
        np.testing.assert_array_equal(values_a, values_b)
    sbatch = json.loads((run / "submissions.json").read_text())[0]["sbatch"]  # settings: sbatch's arguments
    assert "--array=0-7" in sbatch and "--partition=debug" in sbatch and "--time=00:10:00" in sbatch
    assert "--mem=500M" in sbatch and "jobs run-unit" in (run / "slurm-0.sh").read_text()
    status = json.loads(midas("jobs", "status", str(run), "--json", env=env, check=True).stdout)
    assert status["counts"]["done"] == 8 and {u["host"] for u in status["units"]} != {None}

    again = midas("align", *map(str, remote), "--executor", "slurm", "--run-dir", str(run), env=env, timeout=WAIT_S)
    assert again.returncode == 0 and "8 of 8 units done already" in again.stderr
    assert len(json.loads((run / "submissions.json").read_text())) == 1  # nothing submitted

    stream = next((remote[5] / "streams").glob("emht.csv"))
    os.utime(stream, ns=(stream.stat().st_atime_ns, stream.stat().st_mtime_ns + 10**9))  # input changed: stale
    third = midas("align", *map(str, remote), "--executor", "slurm", "--run-dir", str(run), env=env, timeout=WAIT_S)
    assert third.returncode == 0, third.stderr
    assert json.loads((run / "submissions.json").read_text())[-1]["units"] == [5]


def test_a_failed_unit_is_reported_with_its_log_and_the_others_are_kept(slurm, sessions, tmp_path):
    good = copies(sessions[:3], tmp_path / "data")
    broken = Path(shutil.copytree(sessions[3], tmp_path / "data" / "broken"))
    (broken / "manifest.json").write_text("{not json", encoding="utf-8")
    run = tmp_path / "run"
    env = slurm_env(slurm, tmp_path)
    args = ["align", *map(str, good[:2]), str(broken), str(good[2]), "--executor", "slurm", "--run-dir", str(run)]
    result = midas(*args, env=env, timeout=WAIT_S)
    assert result.returncode == 4, result.stderr
    error = result.stderr.strip().splitlines()[-1]
    assert error.startswith("midas: error: 1 of 4 sessions did not finish") and "broken: failed" in error
    assert str(run / "logs" / "unit-2.log") in error
    for session in good:
        assert (session / "derived" / "aligned.npz").is_file()
    status = json.loads(midas("jobs", "status", str(run), "--json", env=env, check=True).stdout)
    states = {u["name"]: u for u in status["units"]}
    assert [states[s.name]["state"] for s in good] == ["done"] * 3
    assert states["broken"]["state"] == "failed" and "manifest.json" in states["broken"]["error"]
    log = Path(states["broken"]["log"]).read_text()
    assert "midas: error:" in log and "manifest.json" in log  # the task's own stderr, in its log
    table = midas("jobs", "status", str(run), env=env, check=True)
    assert "failed" in table.stdout and "1 failed" in table.stderr

    again = midas(*args, env=env, timeout=WAIT_S)  # done units skipped, the broken one tried again
    assert again.returncode == 4 and "3 of 4 units done already" in again.stderr
    assert json.loads((run / "submissions.json").read_text())[-1]["units"] == [2]


def test_no_wait_returns_the_run_folder_at_once(slurm, sessions, tmp_path):
    data = copies(sessions[:2], tmp_path / "data")
    run = tmp_path / "run"
    env = slurm_env(slurm, tmp_path)
    result = midas("align", *map(str, data), "--executor", "slurm", "--run-dir", str(run), "--no-wait", env=env,
                   check=True)
    assert result.stdout.strip() == str(run.resolve()) and "submitted SLURM job" in result.stderr
    deadline = time.monotonic() + WAIT_S
    while True:
        status = json.loads(midas("jobs", "status", str(run), "--json", env=env, check=True).stdout)
        assert set(status["counts"]) >= {"pending", "queued", "running", "done", "failed"}
        if status["counts"]["done"] == 2 or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    assert status["counts"]["done"] == 2, status


def test_train_folds_on_slurm_match_a_local_run(slurm, tmp_path):
    data = tmp_path / "data"
    for i in range(3):
        write_gesture_session(data, "B", i + 1, n_frames=150, seed=i)
    common = ["train", "gestures", str(data), "--model", "baseline-mlp", "--modalities", "emht", "--features", "pos",
              "--split", "loto", "--fold", "all", "--epochs", "2", "--seed", "3", "--no-baseline", "--json"]
    local = midas(*common, "--out", str(tmp_path / "local"), check=True, timeout=WAIT_S)
    env = slurm_env(slurm, tmp_path)
    remote = midas(*common, "--out", str(tmp_path / "remote"), "--executor", "slurm", env=env, timeout=WAIT_S)
    assert remote.returncode == 0, remote.stderr + slurm.log_tail()
    a, b = json.loads(local.stdout), json.loads(remote.stdout)
    assert a["mean"] == b["mean"] and a["pooled"] == b["pooled"]
    folds = lambda root: [{k: v for k, v in f.items() if k != "run"}  # noqa: E731
                          for f in json.loads((root / "cv.json").read_text())["folds"]]
    assert folds(tmp_path / "local") == folds(tmp_path / "remote")
    submissions = json.loads((tmp_path / "remote" / "jobs" / "submissions.json").read_text())
    assert submissions[0]["executor"] == "slurm" and submissions[0]["units"] == [0, 1, 2]

    ablation = ["train", "ablation", str(data), "--models", "baseline-mlp", "--grid", "emht:pos,vel",
                "--split", "loto", "--fold", "1", "--epochs", "1", "--seed", "3", "--json"]
    table = midas(*ablation, "--out", str(tmp_path / "ablation"), "--executor", "slurm", env=env, timeout=WAIT_S)
    assert table.returncode == 0, table.stderr + slurm.log_tail()
    report = json.loads(table.stdout)
    assert [(r["model"], r["features"]) for r in report["results"]] == [("Baseline (MLP)", "pos., vel."),
                                                                         ("Baseline (LR)", "pos., vel.")]
    assert (tmp_path / "ablation" / "table.md").is_file()
    assert len(json.loads((tmp_path / "ablation" / "jobs" / "plan.json").read_text())["units"]) == 2


def test_simulate_dataset_on_slurm_writes_the_same_sessions_as_locally(slurm, tmp_path):
    common = ["simulate", "dataset", "--platform", "raven-ii", "--trials", "2", "--max-seconds", "5", "--seed", "4"]
    local = midas(*common, "--out", str(tmp_path / "local"), check=True, timeout=WAIT_S)
    remote = midas(*common, "--out", str(tmp_path / "remote"), "--executor", "slurm", "--run-dir",
                   str(tmp_path / "run"), env=slurm_env(slurm, tmp_path), timeout=WAIT_S)
    assert remote.returncode == 0, remote.stderr + slurm.log_tail()
    names = [Path(p).name for p in local.stdout.split()]
    assert names == [Path(p).name for p in remote.stdout.split()] and len(names) == 2
    for name in names:
        for stream in (tmp_path / "local" / name / "streams").glob("*.csv"):
            assert stream.read_bytes() == (tmp_path / "remote" / name / "streams" / stream.name).read_bytes()
