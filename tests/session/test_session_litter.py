"""Issue 13 (items 4, 5): temporaries left by interrupted writes, recordings that failed to start, and
finding the newest session after an SSH drop. Everything through the CLI, as a user or script would."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from midas_cli.clock import HostClock
from midas_cli.errors import SessionError
from midas_cli.session.reader import Session
from midas_cli.session.writer import SessionMetadata, SessionWriter
from helpers.cli import REPO, SPEC, copy_session, midas, simulate_trial, write_session

# what a kill or a full disk leaves, one per writer of the session format (find_temporaries' list)
PLANTED = {
    "manifest.json.tmp": b'{"schema_version": 1, "sess',  # disk full while the manifest was replaced
    "streams/emht.npy.tmp": b"\x93NUMPY half a copy",  # killed while finalise wrote a binary copy
    "streams/pedals_gt.csv.tmp": b"seq,t_host_ns\n1,",  # add_stream
    "derived/aligned.values.npy.tmp": b"\x93NUMPY",  # `midas align` killed
    "derived/image_features.npz.tmp.npz": b"PK",  # artifacts.write_npz
    "derived/eval/report.json.tmp": b"{",  # artifacts.write_json below derived/
    "calib/emht_to_mtm.json.tmp": b"{",  # save_calibration
    "labels/gestures.csv.tmp": b"frame,label\n",  # write_frame_labels
}


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate_trial(tmp_path_factory.mktemp("sim"))


@pytest.fixture
def session(simulated: Path, tmp_path: Path) -> Path:
    return copy_session(simulated, tmp_path)


def _digests(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _plant(folder: Path, files: dict[str, bytes]) -> None:
    for rel, data in files.items():
        (folder / rel).parent.mkdir(parents=True, exist_ok=True)
        (folder / rel).write_bytes(data)


# ---- temporaries ------------------------------------------------------------------------------------

def test_verify_reports_every_temporary_and_repair_removes_only_them(session: Path) -> None:
    assert midas("session", "verify", str(session)).returncode == 0
    before = _digests(session)
    _plant(session, PLANTED)
    (session / "video" / "obs_recording.mkv.tmp").write_bytes(b"not ours")  # OBS's folder: left alone

    verify = midas("session", "verify", str(session))
    assert verify.returncode == 4
    problems = [line for line in verify.stdout.splitlines() if "problem:" in line]
    assert len(problems) == len(PLANTED), verify.stdout
    for rel in PLANTED:
        assert any(f"temporary file {rel} " in p and "midas session repair" in p for p in problems), rel
    assert "video/" not in verify.stdout

    repair = midas("session", "repair", str(session))
    assert repair.returncode == 0, repair.stderr
    assert f"status 'complete', removed {len(PLANTED)} temporary file(s)" in repair.stdout
    for rel in PLANTED:
        assert f"removed temporary file {rel}" in repair.stdout
        assert not (session / rel).exists()
    after = _digests(session)
    assert after.pop("video/obs_recording.mkv.tmp")
    assert after == before  # a finished session: nothing but the temporaries touched

    assert midas("session", "verify", str(session)).returncode == 0
    again = midas("session", "repair", str(session), check=True)
    assert "nothing to repair" in again.stdout


def test_repair_json_lists_what_it_removed(session: Path) -> None:
    _plant(session, {"streams/emht.npy.tmp": b"x", "manifest.json.tmp": b""})
    result = midas("session", "repair", "--json", str(session), check=True)
    (report,) = json.loads(result.stdout)
    assert report["removed"] == ["manifest.json.tmp", "streams/emht.npy.tmp"]
    assert report["repaired"] is False and report["restored_manifest"] is False
    verify = midas("session", "verify", "--json", str(session))
    assert verify.returncode == 0 and json.loads(verify.stdout)[0]["problems"] == []


def test_repair_of_a_crashed_session_also_removes_temporaries(tmp_path: Path) -> None:
    folder = write_session(tmp_path, status="recording")
    _plant(folder, {"streams/demo.npy.tmp": b"half"})
    verify = midas("session", "verify", str(folder))
    assert verify.returncode == 4 and "temporary file streams/demo.npy.tmp" in verify.stdout
    repair = midas("session", "repair", str(folder), check=True)
    assert "recovered" in repair.stdout and "removed temporary file streams/demo.npy.tmp" in repair.stdout
    assert not (folder / "streams/demo.npy.tmp").exists()
    assert midas("session", "verify", str(folder)).returncode == 0


def test_a_complete_manifest_left_as_the_temporary_is_put_in_place(session: Path) -> None:
    original = (session / "manifest.json").read_bytes()
    (session / "manifest.json").rename(session / "manifest.json.tmp")  # killed between write and rename
    verify = midas("session", "verify", str(session))
    assert verify.returncode == 4
    assert "manifest.json is missing but manifest.json.tmp holds a complete manifest" in verify.stdout
    repair = midas("session", "repair", str(session), check=True)
    assert "manifest.json was missing" in repair.stdout
    assert (session / "manifest.json").read_bytes() == original
    assert not (session / "manifest.json.tmp").exists()
    assert midas("session", "verify", str(session)).returncode == 0


def test_an_incomplete_manifest_temporary_that_is_the_only_copy_is_refused_and_kept(session: Path) -> None:
    manifest = (session / "manifest.json").read_bytes()
    (session / "manifest.json").unlink()
    (session / "manifest.json.tmp").write_bytes(manifest[: len(manifest) // 2])  # disk full at the start
    _plant(session, {"streams/emht.npy.tmp": b"half"})
    before = _digests(session)
    verify = midas("session", "verify", str(session))
    assert verify.returncode == 4 and "manifest.json.tmp is not a complete manifest" in verify.stdout
    repair = midas("session", "repair", str(session))
    assert repair.returncode == 4
    assert len(repair.stderr.strip().splitlines()) == 1
    assert "not a complete manifest" in repair.stderr and "nothing restored or deleted" in repair.stderr
    assert _digests(session) == before  # not even the other temporary: nothing was decided


def test_a_temporary_beside_an_unreadable_manifest_is_not_deleted(session: Path) -> None:
    _plant(session, {"manifest.json.tmp": (session / "manifest.json").read_bytes()})
    (session / "manifest.json").write_text("{ torn")
    repair = midas("session", "repair", str(session))
    assert repair.returncode == 4 and "cannot read" in repair.stderr
    assert (session / "manifest.json.tmp").is_file()


# ---- failed: a recording that never started -----------------------------------------------------------

def _session_at(root: Path, task: str, start_ns: int, status: str) -> Path:
    """A session of one stream started at ``start_ns`` (host clock), finalised with ``status``: rows only
    if it did not fail (the recorder finalises a failed start with the stream files it had created)."""
    writer = SessionWriter.create(root, SessionMetadata("7", task, 1), HostClock.anchored_now(),
                                  {"demo": {"kind": "test"}}, [SPEC], start_ns=start_ns)
    rows = 0 if status == "failed" else 20
    writer.append("demo", SPEC.format_rows([(i, start_ns + i * 10_000_000, i * 0.5) for i in range(rows)]))
    reason = "could not open obs: connection refused" if status == "failed" else "test"
    writer.finalize(status, reason, start_ns + rows * 10_000_000, {})
    return writer.folder


T0 = 1_700_000_000_000_000_000
HOUR = 3_600 * 10**9


def test_failed_sessions_are_hidden_by_list_unless_all(tmp_path: Path) -> None:
    good = _session_at(tmp_path, "suturing", T0, "complete")
    failed = _session_at(tmp_path, "suturing", T0 + HOUR, "failed")

    listed = midas("session", "list", str(tmp_path), "--json")
    assert listed.returncode == 0
    assert [r["path"] for r in json.loads(listed.stdout)] == [str(good)]
    assert "1 failed session(s) hidden" in listed.stderr and "--all" in listed.stderr

    shown = midas("session", "list", str(tmp_path), "--json", "--all")
    assert {r["path"]: r["status"] for r in json.loads(shown.stdout)} == {str(good): "complete",
                                                                          str(failed): "failed"}
    assert "hidden" not in shown.stderr
    table = midas("session", "list", str(tmp_path), "--all", check=True)
    assert "failed" in table.stdout
    only = midas("session", "list", str(tmp_path), "--status", "failed", "--paths", check=True)
    assert only.stdout == f"{failed}\n"
    paths = midas("session", "list", str(tmp_path), "--paths", check=True)
    assert paths.stdout == f"{good}\n"
    bad = midas("session", "list", str(tmp_path), "--status", "finished")
    assert bad.returncode == 2 and "unknown status finished" in bad.stderr


def test_a_failed_session_is_shown_by_info_reported_by_verify_and_refused_by_readers(tmp_path: Path) -> None:
    failed = _session_at(tmp_path, "suturing", T0, "failed")
    info = midas("session", "info", str(failed), check=True)
    assert "status failed" in info.stdout and "could not open obs" in info.stdout
    assert json.loads(midas("session", "info", "--json", str(failed), check=True).stdout)["status"] == "failed"

    verify = midas("session", "verify", str(failed))
    assert verify.returncode == 4
    assert "the recording failed to start (could not open obs: connection refused)" in verify.stdout

    align = midas("align", str(failed))
    assert align.returncode == 4
    assert align.stderr.strip().count("\n") == 0 and "failed to start" in align.stderr
    with pytest.raises(SessionError, match="failed to start"):
        Session.open(failed)
    assert Session.open(failed, allow_failed=True).status == "failed"


# ---- --latest: finding the session after an SSH drop -------------------------------------------------

def test_latest_is_the_newest_by_start_time_not_by_name(tmp_path: Path) -> None:
    # created newest first, and the newest has the alphabetically first name
    recording = _session_at(tmp_path, "aaa", T0 + 2 * HOUR, "recording")
    failed = _session_at(tmp_path, "aaa", T0 + 3 * HOUR, "failed")
    _session_at(tmp_path, "zzz", T0 + HOUR, "interrupted")
    _session_at(tmp_path, "mmm", T0, "complete")

    latest = midas("session", "list", "--latest", str(tmp_path))
    assert latest.returncode == 0 and latest.stdout == f"{recording}\n"
    assert "1 failed session(s) hidden" in latest.stderr
    document = json.loads(midas("session", "list", "--latest", "--json", str(tmp_path), check=True).stdout)
    assert document == {"path": str(recording), "status": "recording", "start_utc": "2023-11-15T00:13:20.000+00:00",
                        "start_host_ns": T0 + 2 * HOUR, "session_id": recording.name}
    assert midas("session", "list", "--latest", "--all", str(tmp_path), check=True).stdout == f"{failed}\n"
    by_task = midas("session", "list", "--latest", "--task", "zzz", str(tmp_path), check=True)
    assert by_task.stdout.strip().startswith(str(tmp_path / "zzz_S7_T1_"))


def test_latest_with_nothing_to_show_exits_4_with_one_line(tmp_path: Path) -> None:
    empty = midas("session", "list", "--latest", str(tmp_path))
    assert empty.returncode == 4 and empty.stdout == ""
    assert empty.stderr.strip() == f"midas: error: no session under {tmp_path}"
    _session_at(tmp_path, "suturing", T0, "failed")
    only_failed = midas("session", "list", "--latest", "--json", str(tmp_path))
    assert only_failed.returncode == 4 and only_failed.stdout == ""
    assert "1 failed one(s) hidden: --all lists them" in only_failed.stderr.splitlines()[-1]


# ---- make tables DATA=... -----------------------------------------------------------------------------

@pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make")
def test_make_tables_skips_failed_and_unfinished_sessions(tmp_path: Path) -> None:
    data = tmp_path / "data"
    good = _session_at(data, "suturing", T0, "complete")
    failed = _session_at(data, "suturing", T0 + HOUR, "failed")
    crashed = _session_at(data, "suturing", T0 + 2 * HOUR, "recording")
    nested = _session_at(data / "old" / "more", "suturing", T0, "complete")  # not directly under DATA
    result = subprocess.run(
        ["make", "-n", "--no-print-directory", "-C", str(REPO), "tables-dataset", f"TABLES_DATA={data}",
         "TABLES_NAME=data", f"TABLES_DIR={tmp_path / 'results'}", f"MIDAS_BIN={sys.executable} -m midas_cli"],
        capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert f"midas_cli align {good} " in result.stdout
    for other in (failed, crashed, nested):
        assert str(other) not in result.stdout
    warning = next(line for line in result.stderr.splitlines() if "skipping unfinished or failed" in line)
    assert str(failed) in warning and str(crashed) in warning

    for folder in (good, nested):
        shutil.rmtree(folder)
    none = subprocess.run(
        ["make", "-n", "-C", str(REPO), "tables-dataset", f"TABLES_DATA={data}", "TABLES_NAME=data",
         f"MIDAS_BIN={sys.executable} -m midas_cli"], capture_output=True, text=True, timeout=120)
    assert none.returncode != 0 and "no finished session folders" in none.stderr
