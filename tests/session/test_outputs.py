"""Issue 14 item 5: outputs never escape the session or destroy it. Output paths are resolved and
confined, ``--out`` never names a session's own file, writers of one session take turns (a lock), and
the files of one `midas align` run carry one run id that readers check. Everything through the CLI.

No test depends on timing: concurrency is made deterministic by holding the session's lock from the
test (``fcntl.flock``, as midas does) and reading the waiting writer's stderr line."""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from midas_cli.errors import SessionError
from midas_cli.session.derived import read_aligned
from midas_cli.session.labels import write_frame_labels
from helpers.analysis_sessions import raven_session
from helpers.cli import REPO, midas

LOCK = ".midas.lock"  # the documented lock file (README "Where midas writes")


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return raven_session(tmp_path_factory.mktemp("outputs"), duration_s=8.0)


@pytest.fixture
def session(pristine: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "sessions" / pristine.name
    shutil.copytree(pristine, copy)
    return copy


@pytest.fixture(scope="module")
def aligned_pristine(pristine: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    copy = tmp_path_factory.mktemp("aligned") / pristine.name
    shutil.copytree(pristine, copy)
    midas("align", str(copy), check=True)
    return copy


@pytest.fixture
def aligned(aligned_pristine: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "sessions" / aligned_pristine.name
    shutil.copytree(aligned_pristine, copy)
    return copy


def _digests(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _one_error_line(result: subprocess.CompletedProcess, code: int, *words: str) -> str:
    lines = [line for line in result.stderr.strip().splitlines() if not line.startswith("evaluating ")]  # progress
    assert result.returncode == code, result.stderr
    assert len(lines) == 1 and lines[0].startswith("midas: error:"), result.stderr
    assert "Traceback" not in result.stderr
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


# ---- confinement: a linked derived/ or calib/ ------------------------------------------------------

def _link_out(session: Path, sub: str, outside: Path) -> None:
    """Move ``session/sub`` (if any) to ``outside`` and leave a link to it in its place."""
    if (session / sub).exists():
        shutil.move(str(session / sub), str(outside))
    else:
        outside.mkdir()
    (session / sub).symlink_to(outside, target_is_directory=True)


@pytest.mark.parametrize("command", [["align"], ["eval", "correlation"], ["calibrate", "fps-optimize"]])
def test_a_derived_or_calib_folder_linked_outside_is_refused_and_nothing_is_written_there(
        aligned: Path, tmp_path: Path, command: list[str]) -> None:
    outside_derived, outside_calib = tmp_path / "elsewhere-derived", tmp_path / "elsewhere-calib"
    _link_out(aligned, "derived", outside_derived)  # readers may follow it: the table is still read
    _link_out(aligned, "calib", outside_calib)
    before = {**_digests(outside_derived), **_digests(outside_calib)}
    result = midas(*command, str(aligned))
    _one_error_line(result, 4, "outside the session", "link")
    assert {**_digests(outside_derived), **_digests(outside_calib)} == before
    assert not list(tmp_path.glob("elsewhere-*/**/.*.tmp"))


# ---- --out never names a session's own file ------------------------------------------------------

@pytest.mark.parametrize("target", ["manifest.json", "streams/fps.csv", "logs/rules.json"])
def test_fps_optimize_out_naming_a_session_file_is_refused_and_the_session_unchanged(
        aligned: Path, target: str) -> None:
    before = _digests(aligned)
    result = midas("calibrate", "fps-optimize", str(aligned), "--out", str(aligned / target))
    _one_error_line(result, 2, "--out")
    assert _digests(aligned) == before


def test_an_out_link_to_a_manifest_is_refused_too(aligned: Path, tmp_path: Path) -> None:
    link = tmp_path / "rules.json"
    link.symlink_to(aligned / "manifest.json")
    before = _digests(aligned)
    _one_error_line(midas("calibrate", "fps-optimize", str(aligned), "--out", str(link)), 2, "manifest.json")
    assert _digests(aligned) == before


def test_eval_out_folder_inside_the_recording_is_refused(aligned: Path) -> None:
    before = _digests(aligned)
    _one_error_line(midas("eval", "correlation", str(aligned), "--no-plots", "--out", str(aligned / "streams")),
                    2, "--out")
    assert _digests(aligned) == before


def test_a_missing_out_folder_is_created_and_one_that_cannot_be_is_exit_2(session: Path, tmp_path: Path) -> None:
    write_frame_labels(session, [0, 1, 2], ["G1", "G1", "G2"], {"taxonomy": "test", "source": "test"})
    target = tmp_path / "new" / "deeper" / "segments.csv"
    result = midas("labels", "export", str(session), "--format", "csv", "--out", str(target))
    assert result.returncode == 0, result.stderr
    assert target.is_file()
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    _one_error_line(midas("labels", "export", str(session), "--format", "csv", "--out", str(blocker / "x.csv")),
                    2, "--out")


# ---- one writer at a time ----------------------------------------------------------------------

def _hold_lock(session: Path) -> int:
    fd = os.open(session / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    fcntl.flock(fd, fcntl.LOCK_EX)
    return fd


def _popen_midas(*args: str, **env: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "midas_cli", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=REPO, env={**os.environ, "NO_COLOR": "1", "COLUMNS": "200", **env})


def test_a_second_writer_waits_with_a_message_then_writes(session: Path) -> None:
    fd = _hold_lock(session)
    try:
        proc = _popen_midas("align", str(session), MIDAS_LOCK_WAIT_S="300")
        first = proc.stderr.readline()  # blocks until it says it waits (or, unlocked, until it ends)
        assert "being written by another midas" in first and "waiting" in first, first
        assert not (session / "derived" / "aligned.npz").exists()  # it waits before writing anything
    finally:
        os.close(fd)
    _, rest = proc.communicate(timeout=300)
    assert proc.returncode == 0, first + rest
    read_aligned(session)


def test_a_writer_that_cannot_wait_exits_4_with_one_line_and_writes_nothing(session: Path) -> None:
    fd = _hold_lock(session)
    try:
        result = midas("align", str(session), env={"MIDAS_LOCK_WAIT_S": "0"}, timeout=300)
    finally:
        os.close(fd)
    _one_error_line(result, 4, "being written by another midas", "MIDAS_LOCK_WAIT_S")
    assert not (session / "derived").exists() or not list((session / "derived").iterdir())


def test_verify_during_a_write_does_not_wait_for_the_writer_and_says_what_it_skipped(session: Path) -> None:
    """verify never blocks on a writer (the wait is 300 s here: a blocked verify times the test out) and
    does not call the session damaged because another midas is writing its derived files."""
    assert midas("align", str(session)).returncode == 0
    fd = _hold_lock(session)
    try:
        result = midas("session", "verify", str(session), env={"MIDAS_LOCK_WAIT_S": "300"}, timeout=300)
    finally:
        os.close(fd)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "derived/aligned.*: not checked, another midas command is writing" in result.stdout


def test_a_lock_left_by_a_killed_process_never_blocks(session: Path) -> None:
    holder = subprocess.Popen([sys.executable, "-c", "import fcntl, os, sys, time\n"
                               f"fd = os.open({str(session / LOCK)!r}, os.O_RDWR | os.O_CREAT)\n"
                               "fcntl.flock(fd, fcntl.LOCK_EX); print('locked', flush=True); time.sleep(600)"],
                              stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "locked"
    holder.send_signal(signal.SIGKILL)
    holder.wait(timeout=60)
    result = midas("align", str(session), env={"MIDAS_LOCK_WAIT_S": "0"}, timeout=300)
    assert result.returncode == 0, result.stderr


def test_two_align_runs_at_once_leave_one_runs_complete_output(session: Path, tmp_path: Path) -> None:
    expected = {}
    for name, args in (("rate10", ["--downsample", "10"]), ("full", [])):
        copy = tmp_path / name / session.name
        shutil.copytree(session, copy)
        midas("align", str(copy), *args, check=True)
        expected[name] = read_aligned(copy)
    runs = [_popen_midas("align", str(session), "--downsample", "10"), _popen_midas("align", str(session))]
    for proc in runs:
        _, stderr = proc.communicate(timeout=300)
        assert proc.returncode == 0, stderr
    table = read_aligned(session)  # accepted: the three files are of one run
    matches = [name for name, want in expected.items()
               if np.array_equal(table.frame, want.frame) and table.columns == want.columns
               and np.array_equal(np.asarray(table.values), np.asarray(want.values), equal_nan=True)]
    assert len(matches) == 1
    assert table.meta["producer"]["options"]["rate_hz"] == (10.0 if matches == ["rate10"] else None)
    assert midas("session", "verify", str(session)).returncode == 0
    assert not list(session.rglob("*.tmp"))


# ---- files of different runs are refused ---------------------------------------------------------

@pytest.mark.parametrize("swapped", ["aligned.npz", "aligned.values.npy"])
def test_aligned_files_of_different_runs_are_refused_by_every_reader(aligned: Path, tmp_path: Path,
                                                                     swapped: str) -> None:
    kept = tmp_path / swapped
    shutil.copy2(aligned / "derived" / swapped, kept)  # from the causal run
    midas("align", str(aligned), "--method", "nearest", check=True)  # same shape, other values
    shutil.copy2(kept, aligned / "derived" / swapped)
    with pytest.raises(SessionError, match="different `midas align` runs"):
        read_aligned(aligned)
    _one_error_line(midas("eval", "correlation", str(aligned), "--no-plots"), 4, "different `midas align` runs")
    verify = midas("session", "verify", str(aligned))
    assert verify.returncode == 4 and "different `midas align` runs" in verify.stdout + verify.stderr


def test_the_aligned_table_records_what_produced_it(aligned: Path) -> None:
    producer = read_aligned(aligned).meta["producer"]
    assert producer["command"] == "midas align" and producer["options"]["method"] == "causal"
    assert producer["midas_version"] and producer["written_utc"].endswith("Z") and len(producer["run_id"]) == 32
    assert producer["inputs"]["streams/fps.csv"]["sha256"] and producer["inputs"]["streams/fps.csv"]["bytes"] > 0
