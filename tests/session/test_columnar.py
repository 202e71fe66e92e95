"""Binary stream copies (streams/<name>.npy): written at finalise, identical to the CSV, used by align
only while they match the CSV, and checked by `session verify`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from helpers.analysis_sessions import raven_session
from helpers.cli import midas
from midas_cli.analysis.align import align_session
from midas_cli.clock import HostClock
from midas_cli.session.columnar import parse_csv_columns
from midas_cli.session.reader import Session
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
from midas_cli.session.writer import SessionMetadata, SessionWriter


def _equal(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype.names == b.dtype.names and len(a) == len(b) and all(
        np.array_equal(a[f], b[f], equal_nan=b[f].dtype.kind == "f") for f in b.dtype.names)


def test_finalise_writes_copies_equal_to_the_csv_and_align_gives_the_same_table(tmp_path: Path) -> None:
    session_path = raven_session(tmp_path, duration_s=6.0)
    session = Session.open(session_path)
    for name in session.stream_names:
        entry = session.manifest["streams"][name]
        assert entry["binary"] == {"file": f"streams/{name}.npy", "rows": entry["samples"],
                                   "csv_sha256": entry["sha256"]}
        copy = session.read_columns(name)
        assert isinstance(copy, np.memmap), f"{name}: the copy is memory-mapped, not parsed"
        assert _equal(copy, parse_csv_columns(session.stream_path(name), session.stream_spec(name)))
    from_copies = align_session(session_path)
    for npy in (session_path / "streams").glob("*.npy"):
        npy.unlink()
    from_csv = align_session(session_path)
    assert from_copies.columns == from_csv.columns
    assert np.array_equal(from_copies.values, from_csv.values, equal_nan=True)


def test_a_csv_changed_after_the_copy_is_read_from_the_csv(tmp_path: Path) -> None:
    session_path = raven_session(tmp_path, duration_s=3.0)
    session = Session.open(session_path)
    rows = len(session.read_columns("fps"))
    with open(session.stream_path("fps"), "a", encoding="utf-8") as fh:
        last = session.stream_path("fps").read_text().splitlines()[-1].split(",")
        fh.write(",".join([str(int(last[0]) + 1), str(int(last[1]) + 4_000_000), *last[2:]]) + "\n")
    again = Session.open(session_path).read_columns("fps")
    assert len(again) == rows + 1 and not isinstance(again, np.memmap)


def test_verify_passes_good_copies_and_reports_a_tampered_one(tmp_path: Path) -> None:
    session_path = raven_session(tmp_path, duration_s=3.0)
    assert midas("session", "verify", str(session_path)).returncode == 0
    npy = session_path / "streams" / "emht.npy"
    copy = np.load(npy).copy()
    copy["s1_x_mm"][5] += 1.0
    np.save(npy, copy)
    result = midas("session", "verify", str(session_path), "--json")
    assert result.returncode == 4
    problems = json.loads(result.stdout)[0]["problems"]
    assert problems == ["emht: binary copy streams/emht.npy differs from the CSV; delete it and readers parse the CSV"]


def test_int_columns_stay_int64_unless_they_have_missing_values(tmp_path: Path) -> None:
    spec = StreamSpec("demo", "demo", (SEQ, T_HOST, Column("count", "int"), Column("gap", "int"),
                                       Column("x", "float", decimals=2)), 10.0)
    writer = SessionWriter.create(tmp_path, SessionMetadata("1", "demo", 1), HostClock(0),
                                  {"demo": {"kind": "test"}}, [spec], start_ns=10**18)
    writer.append("demo", spec.format_rows([(0, 10**18, 7, None, 0.25), (1, 10**18 + 10**8, 9, 3, None)]))
    writer.finalize("complete", "test", 10**18 + 10**9, {})
    table = Session.open(writer.folder).read_columns("demo")
    assert table.dtype["count"] == np.int64 and table.dtype["t_host_ns"] == np.int64
    assert table.dtype["gap"] == np.float64 and np.isnan(table["gap"][0]) and table["gap"][1] == 3
    assert table["t_host_ns"][1] == 10**18 + 10**8, "host ns stay exact"
    assert table["x"][0] == 0.25 and np.isnan(table["x"][1])


def test_a_deleted_copy_is_not_a_problem_and_the_csv_is_read(tmp_path: Path) -> None:
    session_path = raven_session(tmp_path, duration_s=3.0)
    (session_path / "streams" / "fps.npy").unlink()  # what verify suggests for a bad copy
    assert midas("session", "verify", str(session_path)).returncode == 0
    table = Session.open(session_path).read_columns("fps")
    assert not isinstance(table, np.memmap) and len(table) > 0


def test_align_gives_the_same_table_when_its_column_block_has_to_grow(tmp_path: Path, monkeypatch) -> None:
    import midas_cli.analysis.align as align

    session_path = raven_session(tmp_path, duration_s=3.0)
    roomy = align_session(session_path)

    class Cramped(align.ColumnSet):  # every claim beyond 8 columns reallocates the block
        def __init__(self, n_frames: int) -> None:
            super().__init__(n_frames, capacity=8)

    monkeypatch.setattr(align, "ColumnSet", Cramped)
    cramped = align_session(session_path)
    assert cramped.columns == roomy.columns and len(roomy.columns) > 8
    assert np.array_equal(cramped.values, roomy.values, equal_nan=True)
