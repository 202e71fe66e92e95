"""Issue 23 item 5: inputs that were internal errors (exit 1, a traceback), read until memory ran out, or
passed with the wrong exit code are one `midas: error:` line with the documented exit code: a header-only
stream to calibrate, a session whose derived/ is a file or whose data no ablation cell can use, a run
folder with wrong types in its plan or markers, and rig files that are devices, FIFOs, deeply nested or not
UTF-8 (config files of every such kind: tests/commands/test_property_config.py)."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import pytest

from helpers.analysis_sessions import raven_session
from helpers.cli import midas
from helpers.gesture_sessions import write_gesture_session
from midas_cli.devices.rigconfig import load_rig
from midas_cli.errors import ConfigError
from midas_cli.jobs.rundir import Plan, RunDir, Unit
from midas_cli.models.ablation import finish_ablation
from midas_cli.models.train import TrainConfig


def one_error_line(result, code: int) -> str:
    """The error line of a refused command: its exit code is ``code`` and stderr ends with one error line
    (progress lines may come before it), no traceback."""
    assert result.returncode == code, result.stderr
    lines = result.stderr.strip().splitlines()
    assert lines and lines[-1].startswith("midas: error: "), result.stderr
    assert "Traceback" not in result.stderr and sum("error" in line for line in lines) == 1, result.stderr
    return lines[-1]


def test_calibrating_on_a_header_only_stream_names_the_file(tmp_path):
    session = raven_session(tmp_path, trial=1, duration_s=3.0)
    emht = session / "streams" / "emht.csv"
    emht.write_text(emht.read_text(encoding="utf-8").splitlines()[0] + "\n", encoding="utf-8")
    line = one_error_line(midas("calibrate", "emht", str(session)), 4)
    assert "emht.csv: 0 data rows" in line


@pytest.fixture(scope="module")
def gestures(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("gestures")
    for i in range(3):
        write_gesture_session(root, "B", i + 1, n_frames=120, seed=i)
    return root


ABLATION = ["--models", "baseline-mlp", "--grid", "emht:pos", "--split", "loto", "--fold", "1", "--epochs", "1",
            "--no-baseline"]


def damaged_copy(gestures: Path, tmp_path: Path, damage) -> Path:
    data = Path(shutil.copytree(gestures, tmp_path / "data"))
    damage(min(data.iterdir()))
    return data


def _derived_a_file(session: Path) -> None:
    shutil.rmtree(session / "derived")
    (session / "derived").write_text("not a folder\n")


@pytest.mark.parametrize(("damage", "needle"), [
    (_derived_a_file, "derived/aligned.json: Not a directory"),
    (lambda s: (s / "labels" / "gestures.csv").write_text("junk,,,\n"), "gestures.csv: expected columns"),
])
def test_train_ablation_on_bad_data_is_a_data_error(gestures, tmp_path, damage, needle):
    data = damaged_copy(gestures, tmp_path, damage)
    result = midas("train", "ablation", str(data), *ABLATION, "--out", str(tmp_path / "out"))
    assert needle in one_error_line(result, 4)


def test_an_ablation_no_cell_could_run_has_the_exit_code_of_its_first_reason(tmp_path):
    base = TrainConfig(split="loto", fold=1, epochs=1)
    cell = {"model": "baseline-mlp", "row": "emht_pos"}
    for codes, expected in (([4, 2], 4), ([2, 4], 2), ([3], 3), ([None], 2), (["4"], 2), ([True], 2)):
        skipped = [{"skipped": {**cell, "reason": f"reason {c}", **({} if c is None else {"exit_code": c})}}
                   for c in codes]
        with pytest.raises(ConfigError, match="no ablation row could run") as caught:
            finish_ablation(tmp_path, skipped, base, cv=False)
        assert caught.value.exit_code == expected, codes


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory) -> Path:
    """A run folder of one done unit and one running, written through the library (nothing run)."""
    run = RunDir(tmp_path_factory.mktemp("run") / "run")
    run.write_plan(Plan("align", [Unit("a", {"x": 1}, "f1"), Unit("b", {"x": 2}, "f2")]))
    run.write_marker(0, "done", {"unit": 0, "name": "a", "fingerprint": "f1", "seconds": 1.5, "host": "h",
                                 "outputs": []})
    run.write_marker(1, "running", {"unit": 1, "name": "b", "host": "elsewhere", "pid": 12})
    run.add_submission({"executor": "local", "units": [0, 1], "jobs": 1})
    return run.path


def test_jobs_status_reads_the_undamaged_run_folder(run_folder):
    status = json.loads(midas("jobs", "status", str(run_folder), "--json", check=True).stdout)
    assert [u["state"] for u in status["units"]] == ["done", "running"] and status["units"][0]["seconds"] == 1.5


@pytest.mark.parametrize(("file", "content", "needle"), [
    ("units/0/done.json", {"fingerprint": "f1", "seconds": "slow"}, 'done.json: seconds = "slow" should be a number'),
    ("units/0/done.json", {"fingerprint": "f1", "outputs": "x"}, "outputs = \"x\" should be a list of strings"),
    ("units/0/done.json", {"fingerprint": ["f1"]}, "fingerprint = [\"f1\"] should be a string"),
    ("units/1/running.json", {"host": "elsewhere", "pid": "12"}, 'running.json: pid = "12" should be an integer'),
    ("units/1/running.json", {"host": 7, "pid": 12}, "host = 7 should be a string"),
    ("submissions.json", [{"executor": "local", "units": "0"}], "entry 0: units = \"0\" should be a list"),
    ("plan.json", {"task": "align", "units": {}}, "plan.json is malformed"),
    ("plan.json", {"task": "align", "units": []}, "no units"),
    ("plan.json", {"task": "align", "units": [{"index": 0, "name": "a", "args": {}}]}, "unit 0: no fingerprint"),
    ("plan.json", {"task": "align", "units": [{"index": 3, "name": "a", "args": {}, "fingerprint": "f"}]},
     "unit 0 says index 3"),
    ("plan.json", b'{"task": "align", "units": [', "plan.json is malformed"),  # cut short: not JSON
])
def test_jobs_status_refuses_a_run_folder_with_wrong_types(run_folder, tmp_path, file, content, needle):
    run = Path(shutil.copytree(run_folder, tmp_path / "run"))
    (run / file).write_bytes(content if isinstance(content, bytes) else json.dumps(content).encode())
    line = one_error_line(midas("jobs", "status", str(run), "--json"), 4)
    assert needle in line and file.split("/")[-1] in line


@pytest.mark.parametrize("kind", ["device", "fifo", "folder", "deep", "latin-1", "huge"])
def test_load_rig_refuses_files_that_are_no_rig_files(tmp_path, kind):
    rig = {"device": Path("/dev/zero"), "folder": tmp_path}.get(kind, tmp_path / "rig.toml")
    if kind == "fifo":
        os.mkfifo(rig)  # nobody writes to it: a blocking read would hang
    elif kind == "deep":
        rig.write_text("[rig]\nname = " + "[" * 5000 + "]" * 5000 + "\n")
    elif kind == "latin-1":
        rig.write_bytes('[rig]\nname = "Tübingen"\n'.encode("latin-1"))
    elif kind == "huge":
        rig.write_text("[rig]\n" + "# padding\n" * 200_000)
    expected = {"device": "not a regular file", "fifo": "not a regular file", "folder": "is a folder",
                "deep": "nested too deeply", "latin-1": "not UTF-8 text (byte 15)", "huge": "larger than 1 MiB"}[kind]
    with pytest.raises(ConfigError, match=re.escape(f"rig file {rig} ") + ".*" + re.escape(expected)):
        load_rig(rig)


def test_a_rig_of_dev_zero_is_refused_from_the_flag_the_argument_and_the_config(tmp_path):
    config = tmp_path / "config.toml"
    config.write_text('[record]\nrig = "/dev/zero"\n', encoding="utf-8")
    env = {"MIDAS_CONFIG": str(config), "MIDAS_RIG": ""}
    meta = ["--subject", "1", "--task", "t", "--trial", "1", "--duration", "1", "--no-tui", "--out", str(tmp_path / "o")]
    for args in (["rig", "check", "/dev/zero"], ["rig", "check"], ["record", "--rig", "/dev/zero", *meta],
                 ["record", *meta]):
        line = one_error_line(midas(*args, env=env, timeout=60), 2)
        assert "rig file /dev/zero is not a regular file" in line, args
    assert not (tmp_path / "o").exists()
