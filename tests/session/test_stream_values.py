"""Verify means verified (issue 14 items 3-5): every value against its column's type and range, typed
manifests, torn tails used and reported, damage inside a file and non-regular files refused (exit 4,
one line naming the file and line)."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest

from helpers.cli import copy_session, midas, simulate_trial


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # easy: the line counts asserted below are those of this exact trial (the uniform simulator's)
    return simulate_trial(tmp_path_factory.mktemp("sim"), "--difficulty", "easy")


@pytest.fixture
def session(simulated: Path, tmp_path: Path) -> Path:
    return copy_session(simulated, tmp_path)


def _set_field(session: Path, stream: str, line: int, column: int, text: bytes) -> None:
    """Put ``text`` in field ``column`` of ``line`` (1-based, header = 1) of a stream, then describe
    the file in the manifest again (as if the recorder had written it so) and drop its binary copy."""
    path = session / "streams" / f"{stream}.csv"
    lines = path.read_bytes().split(b"\n")
    fields = lines[line - 1].split(b",")
    fields[column] = text
    lines[line - 1] = b",".join(fields)
    path.write_bytes(b"\n".join(lines))
    _describe_again(session, stream)


def _describe_again(session: Path, stream: str) -> None:
    manifest = json.loads((session / "manifest.json").read_text())
    entry = manifest["streams"][stream]
    data = (session / entry["file"]).read_bytes()
    entry.update(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
    (session / entry.pop("binary")["file"]).unlink()
    (session / "manifest.json").write_text(json.dumps(manifest))


def _one_error_line(result, *needles: str) -> str:
    errors = [line for line in result.stderr.splitlines() if line.startswith("midas: error:")]
    assert result.returncode == 4, result.stderr
    assert len(errors) == 1 and "Traceback" not in result.stderr, result.stderr
    for needle in needles:
        assert needle in errors[0], errors[0]
    return errors[0]


@pytest.mark.parametrize("stream, column, text", [
    ("emht", 3, b"abc"),  # text in a float column
    ("emht", 3, b"inf"),
    ("emht", 4, b"1e308"),  # finite, absurd
    ("emht", 5, b"nan"),  # missing values are empty fields, never text
    ("fps", 3, b"123456789012345678901234"),  # overflows int64 (was an internal error)
    ("fps", 12, b"2"),  # a bool column (pedal pressed)
    ("emht", 3, b"\xff\xfe"),  # not UTF-8 text
])
def test_bad_values_are_refused_by_verify_and_readers(session: Path, stream: str, column: int, text: bytes) -> None:
    _set_field(session, stream, 100, column, text)
    verify = midas("session", "verify", str(session))
    assert verify.returncode == 4 and f"{stream}.csv line 100" in verify.stdout, verify.stdout
    _one_error_line(midas("align", str(session)), f"streams/{stream}.csv line 100")


def test_a_torn_tail_is_used_up_to_the_last_whole_line_with_one_warning(session: Path) -> None:
    path = session / "streams" / "emht.csv"
    with open(path, "r+b") as fh:  # a complete session whose CSV lost the end of its last line
        fh.truncate(path.stat().st_size - 20)
    result = midas("align", str(session), "--json")
    assert result.returncode == 0, result.stderr
    warnings = [line for line in result.stderr.splitlines() if "torn" in line]
    assert len(warnings) == 1 and "emht.csv" in warnings[0] and "2571 whole lines" in warnings[0], result.stderr
    assert json.loads(result.stdout)[0]["frames"] == 321


def test_a_torn_line_inside_the_file_is_refused(session: Path) -> None:
    path = session / "streams" / "emht.csv"
    lines = path.read_bytes().split(b"\n")
    lines[99] = lines[99][:40]  # line 100 cut short, whole lines after it
    path.write_bytes(b"\n".join(lines))
    _one_error_line(midas("align", str(session)), "emht.csv line 100", "fields")


def test_a_fifo_in_place_of_a_stream_is_refused_without_blocking(session: Path) -> None:
    path = session / "streams" / "emht.csv"
    path.unlink()
    os.mkfifo(path)
    _one_error_line(midas("align", str(session), timeout=60), "emht.csv", "not a regular file")
    verify = midas("session", "verify", str(session), timeout=60)
    assert verify.returncode == 4 and "not a regular file (a FIFO)" in verify.stdout, verify.stdout


def test_host_time_going_backwards_is_flagged_by_align(session: Path) -> None:
    path = session / "streams" / "emht.csv"
    lines = path.read_bytes().split(b"\n")
    lines[99], lines[100] = lines[100], lines[99]  # rows 100 and 101 swapped
    path.write_bytes(b"\n".join(lines))
    _describe_again(session, "emht")
    result = midas("align", str(session), "--json")
    assert result.returncode == 0, result.stderr
    flagged = [w for w in json.loads(result.stdout)[0]["warnings"] if "goes backwards" in w]
    assert len(flagged) == 1 and "emht.csv" in flagged[0] and "line 101" in flagged[0], flagged
    assert "goes backwards" in result.stderr


def test_a_csv_edited_behind_the_manifests_back_is_read_not_its_stale_binary_copy(session: Path) -> None:
    """Two host times swapped keep the file's size: the binary copy made at finalise no longer matches
    the CSV (the record), so align reads the CSV and flags what is in it; verify names the edit."""
    path = session / "streams" / "emht.csv"
    lines = path.read_bytes().split(b"\n")
    lines[99], lines[100] = lines[100], lines[99]
    path.write_bytes(b"\n".join(lines))
    assert (session / "streams" / "emht.npy").is_file()
    result = midas("align", str(session), "--json")
    assert result.returncode == 0, result.stderr
    flagged = [w for w in json.loads(result.stdout)[0]["warnings"] if "goes backwards" in w]
    assert len(flagged) == 1 and "emht.csv" in flagged[0] and "line 101" in flagged[0], flagged
    assert midas("session", "verify", str(session)).returncode == 4


@pytest.mark.parametrize("field, value", [
    (("streams",), []),
    (("devices",), []),
    (("start", "host_ns"), "1720003600000000000"),
    (("metadata", "trial"), "1"),
    (("streams", "emht", "columns"), "seq,t_host_ns"),
    (("streams", "emht", "samples"), "2572"),
    (("streams", "emht", "columns", 3, "decimals"), 3.5),
    (("schema_version",), True),
])
def test_a_mistyped_manifest_is_refused_naming_the_field(session: Path, field: tuple, value: object) -> None:
    manifest = json.loads((session / "manifest.json").read_text())
    parent = manifest
    for key in field[:-1]:
        parent = parent[key]
    parent[field[-1]] = value
    (session / "manifest.json").write_text(json.dumps(manifest))
    _one_error_line(midas("session", "info", str(session)), str(field[-1]))
    assert midas("session", "verify", str(session)).returncode == 4


def test_a_burst_of_rows_gets_no_measured_rate() -> None:
    """13 rows stamped within 36 µs (a device that opened late and delivered its buffer at once) once
    reported 354,180 Hz for a 240 Hz stream; a span that short measures nothing."""
    from midas_cli.session.streamfile import summarize_bytes
    from helpers.cli import SPEC

    burst = SPEC.header_line() + SPEC.format_rows([(k, 10**18 + 3_000 * k, 0.5) for k in range(13)])
    assert summarize_bytes(burst.encode(), SPEC).measured_rate_hz is None
    steady = SPEC.header_line() + SPEC.format_rows([(k, 10**18 + 10_000_000 * k, 0.5) for k in range(51)])
    assert abs(summarize_bytes(steady.encode(), SPEC).measured_rate_hz - 100.0) < 1e-9
