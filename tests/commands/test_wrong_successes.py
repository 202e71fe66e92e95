"""Issue 23 item 4: commands that exited 0 on data they should have refused. A broken manifest under
`calibrate fps-optimize`; a host time far outside the session that `verify` passed and `replay` waited
on for ever; `eval` / `train` / `calibrate fps-optimize` on a derived/aligned table older than its streams."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from midas_cli.analysis.align import align_and_write
from midas_cli.errors import SessionError
from midas_cli.session.derived import read_aligned
from midas_cli.session.labels import write_frame_labels
from midas_cli.session.manifest import write_manifest
from midas_cli.session.reader import Session
from midas_cli.session.streamfile import summarize_stream
from helpers.analysis_sessions import raven_session
from helpers.cli import midas


def assert_one_error(result, code: int, *needles: str) -> str:
    """Exit ``code``, stderr ending in the one `midas: error:` line, holding every needle (progress
    lines may come before it), no traceback; that line."""
    lines = result.stderr.strip().splitlines()
    errors = [line for line in lines if line.startswith("midas: error: ")]
    assert result.returncode == code and errors == lines[-1:], result.stderr
    assert "Traceback" not in result.stderr
    for needle in needles:
        assert needle in errors[0], errors[0]
    return errors[0]


@pytest.fixture(scope="module")
def aligned(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 10 s Raven-II-like session (pedal ground truth from the robot's clutch), aligned."""
    session = raven_session(tmp_path_factory.mktemp("wrongok"), duration_s=10.0)
    align_and_write(session)
    return session


def copy_session(session: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(session, tmp_path / session.name))


def test_fps_optimize_refuses_a_broken_manifest_and_writes_nothing(aligned: Path, tmp_path: Path) -> None:
    session = copy_session(aligned, tmp_path)
    (session / "manifest.json").write_text("{")
    assert_one_error(midas("calibrate", "fps-optimize", str(session)), 4, "manifest.json")
    assert not (session / "calib" / "fps_optimized.json").exists()


def _touch_after_table(session: Path, rel: str) -> None:
    """Give ``rel`` a modification time 1 s after the aligned table's."""
    made = (session / "derived" / "aligned.json").stat().st_mtime_ns
    os.utime(session / rel, ns=(made + 10**9, made + 10**9))


def _edit_keeping_size(session: Path, rel: str) -> None:
    """Change the last digit of the file's last line (a hand edit that keeps the size), dated after the table."""
    path = session / rel
    data = bytearray(path.read_bytes())
    digit = max(i for i in range(len(data)) if chr(data[i]).isdigit())
    data[digit] = ord("1") if data[digit] != ord("1") else ord("2")
    path.write_bytes(bytes(data))
    _touch_after_table(session, rel)


def test_eval_train_and_fps_optimize_refuse_a_table_older_than_its_streams_until_realigned(aligned: Path,
                                                                                           tmp_path: Path) -> None:
    session = copy_session(aligned, tmp_path)
    frames = Session.open(session).read_stream("video")["seq"].to_numpy()
    write_frame_labels(session, frames, ["G1"] * len(frames), {"taxonomy": "test"})  # what train reads first
    _edit_keeping_size(session, "streams/fps.csv")
    for args in (("eval", "pedals", str(session), "--out", str(tmp_path / "eval"), "--no-plots"),
                 ("calibrate", "fps-optimize", str(session)),
                 ("train", "gestures", str(session), "--epochs", "1", "--out", str(tmp_path / "train"))):
        assert_one_error(midas(*args), 4, "streams/fps.csv", f"`midas align {session}`")
    assert not (session / "calib" / "fps_optimized.json").exists()
    midas("align", str(session), check=True)
    midas("calibrate", "fps-optimize", str(session), check=True)


def test_a_stream_changed_in_the_manifest_makes_the_table_stale(aligned: Path, tmp_path: Path) -> None:
    """A session recorded, repaired or imported again: the manifest's sha256 is no longer the table's."""
    session = copy_session(aligned, tmp_path)
    manifest = json.loads((session / "manifest.json").read_text())
    manifest["streams"]["emht"]["sha256"] = "0" * 64
    (session / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(SessionError, match="streams/emht.csv \\(its sha256 or size in the manifest\\)"):
        read_aligned(session)
    assert read_aligned(session, current=False).columns  # `verify` still reads it: older is not damaged


def test_a_copy_that_only_touched_the_times_is_still_current(aligned: Path, tmp_path: Path) -> None:
    session = copy_session(aligned, tmp_path)
    for stream in (session / "streams").glob("*.csv"):
        _touch_after_table(session, f"streams/{stream.name}")
    assert read_aligned(session).columns == read_aligned(aligned).columns


def test_the_align_command_given_repeats_the_options_the_table_was_made_with(aligned: Path, tmp_path: Path) -> None:
    session = copy_session(aligned, tmp_path)
    midas("align", str(session), "--method", "nearest", "--downsample", "10", "--csv", check=True)
    _edit_keeping_size(session, "streams/video.csv")
    with pytest.raises(SessionError, match=f"`midas align {session} --method nearest --downsample 10 --csv`"):
        read_aligned(session)


def _shift_last_time(session: Path, stream: str, by_ns: int, describe: bool) -> int:
    """Add ``by_ns`` to the last row's t_host_ns (its line number returned) and, with ``describe``, put
    the file's new sha256, size and times in the manifest (else only sha256 and size: a manifest that
    says nothing odd)."""
    path = session / "streams" / f"{stream}.csv"
    lines = path.read_bytes().splitlines(keepends=True)
    fields = lines[-1].split(b",")
    fields[1] = str(int(fields[1]) + by_ns).encode()
    path.write_bytes(b"".join(lines[:-1]) + b",".join(fields))
    manifest = Session.open(session).manifest
    found = summarize_stream(path, Session(session, manifest).stream_spec(stream)).manifest_fields()
    entry = manifest["streams"][stream]
    entry.update(found if describe else {k: found[k] for k in ("sha256", "bytes")})
    entry.pop("binary", None)
    (path.with_suffix(".npy")).unlink(missing_ok=True)
    write_manifest(session, manifest)
    return len(lines)


@pytest.fixture(scope="module")
def far_time(aligned: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int]:
    """A copy whose last emht row is 1e17 ns (3 years) late, the manifest describing the file as it is."""
    session = copy_session(aligned, tmp_path_factory.mktemp("far"))
    shutil.rmtree(session / "derived")
    return session, _shift_last_time(session, "emht", 10**17, describe=True)


def test_verify_names_the_file_line_and_value_of_a_time_far_outside_the_session(far_time) -> None:
    session, line = far_time
    result = midas("session", "verify", str(session))
    assert result.returncode == 4
    value = Session.open(session).manifest["streams"]["emht"]["last_t_host_ns"]
    assert f"streams/emht.csv line {line}: t_host_ns {value} is far outside" in result.stdout + result.stderr


def test_replay_refuses_a_time_far_outside_the_session_instead_of_waiting(far_time) -> None:
    session, _line = far_time
    assert_one_error(midas("replay", str(session), "--to", "lsl", "--delay", "0", timeout=60), 4,
                     "streams/emht.csv", "far outside")


def test_a_time_a_little_after_the_stop_is_fine(aligned: Path, tmp_path: Path) -> None:
    """Within the margin (a minute, or the session's length): a device's last read after the stop time."""
    session = copy_session(aligned, tmp_path)
    _shift_last_time(session, "emht", 5 * 10**9, describe=True)
    midas("session", "verify", str(session), check=True)
