"""Session folder v1: manifest round trip, reader refusals, naming, verify and repair."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from midas_cli.errors import SessionError
from midas_cli.session.integrity import repair_session, verify_session
from midas_cli.session.manifest import load_manifest, write_manifest
from midas_cli.session.reader import Session, find_sessions
from midas_cli.session.schema import StreamSpec
from midas_cli.processes import process_start
from midas_cli.session.folder import STAGING_DIR, make_session_folder
from helpers.cli import SPEC, write_session


def test_manifest_round_trip_keeps_every_field(small_session: Path) -> None:
    manifest = load_manifest(small_session)
    manifest["metadata"]["operator_note"] = "ünïcode, \"quotes\" and a\nnewline"
    write_manifest(small_session, manifest)
    again = load_manifest(small_session)
    assert again == manifest
    assert StreamSpec.from_manifest("demo", again["streams"]["demo"]) == SPEC
    assert not (small_session / "manifest.json.tmp").exists()


def test_reader_reads_exact_host_times(small_session: Path) -> None:
    session = Session.open(small_session)
    frame = session.read_stream("demo")
    assert list(frame.columns) == ["seq", "t_host_ns", "x_mm"]
    assert frame["t_host_ns"].dtype == "int64"
    assert (frame["t_host_ns"].diff().dropna() == 10_000_000).all()  # no float rounding of ns
    assert frame["x_mm"].iloc[3] == 1.5
    assert session.manifest["streams"]["demo"]["samples"] == 50


def test_reader_refuses_unknown_schema_version(small_session: Path) -> None:
    path = small_session / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["schema_version"] = 2
    path.write_text(json.dumps(manifest))
    with pytest.raises(SessionError, match="schema_version 2"):
        Session.open(small_session)


@pytest.mark.parametrize("bad", ["../outside.csv", "/etc/passwd", "streams/../../x.csv", "a\\b.csv"])
def test_reader_refuses_paths_escaping_the_session(small_session: Path, bad: str) -> None:
    path = small_session / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["streams"]["demo"]["file"] = bad
    path.write_text(json.dumps(manifest))
    with pytest.raises(SessionError, match="escapes|relative"):
        Session.open(small_session)


def test_reader_refuses_symlink_out_of_the_session(small_session: Path, tmp_path: Path) -> None:
    outside = tmp_path / "elsewhere.csv"
    outside.write_text("seq,t_host_ns,x_mm\n")
    (small_session / "streams" / "link.csv").symlink_to(outside)
    path = small_session / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["streams"]["demo"]["file"] = "streams/link.csv"
    path.write_text(json.dumps(manifest))
    with pytest.raises(SessionError, match="link"):
        Session.open(small_session)


def _note_name(folder: Path, name: str) -> None:
    (folder / "name.txt").write_text(name)


def test_sessions_are_never_overwritten(tmp_path: Path) -> None:
    first = make_session_folder(tmp_path, "demo_S1_T1", 1_700_000_000_000_000_000, _note_name)
    second = make_session_folder(tmp_path, "demo_S1_T1", 1_700_000_000_000_000_000, _note_name)
    assert first != second and first.name == "demo_S1_T1_20231114T221320Z"
    assert second.name == first.name + "_2"
    assert (first / "name.txt").read_text() == first.name and (second / "name.txt").read_text() == second.name
    assert sorted(p.name for p in tmp_path.iterdir()) == [first.name, second.name]  # no staging left


def test_a_session_folder_appears_only_with_what_was_written_into_it(tmp_path: Path) -> None:
    seen = []

    def populate(folder: Path, name: str) -> None:
        (folder / "manifest.json").write_text("{}")
        # not under its name yet, and not where a script watching <out>/*/manifest.json would find it
        seen.append((sorted(p.name for p in tmp_path.iterdir()), folder.parent.name, list(tmp_path.glob("*/manifest.json"))))

    folder = make_session_folder(tmp_path, "demo_S1_T1", 1_700_000_000_000_000_000, populate)
    assert seen == [([STAGING_DIR], STAGING_DIR, [])]
    assert [p.name for p in tmp_path.iterdir()] == [folder.name] and (folder / "manifest.json").is_file()


def test_a_failed_start_leaves_no_folder_at_all(tmp_path: Path) -> None:
    def populate(folder: Path, name: str) -> None:
        (folder / "manifest.json").write_text("{}")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        make_session_folder(tmp_path, "demo_S1_T1", 1_700_000_000_000_000_000, populate)
    assert list(tmp_path.iterdir()) == []


def test_staging_left_by_a_killed_start_is_skipped_and_then_removed(tmp_path: Path) -> None:
    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    staging = tmp_path / STAGING_DIR
    dead = staging / f"{int(ended.stdout)}-1-0123abcd"  # its process has ended
    mine = staging / f"{os.getpid()}-{process_start(os.getpid())}-89abcdef"  # still being made
    reused = staging / f"{os.getpid()}-1-00000000"  # this PID, another start time: ended
    for folder in (dead, mine, reused):
        write_session(folder)
    assert list(find_sessions(tmp_path)) == []  # a session being made is no session yet
    folder = make_session_folder(tmp_path, "demo_S1_T1", 1_700_000_000_000_000_000, _note_name)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([folder.name, STAGING_DIR])
    assert [p.name for p in staging.iterdir()] == [mine.name]
    shutil.rmtree(mine)
    second = make_session_folder(tmp_path, "demo_S1_T1", 1_700_000_000_000_000_000, _note_name)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([folder.name, second.name])  # the empty one goes


def test_a_linked_staging_folder_is_refused_and_nothing_behind_it_is_touched(tmp_path: Path) -> None:
    elsewhere = tmp_path / "elsewhere"
    (elsewhere / "1-1-0123abcd").mkdir(parents=True)  # named like a killed start's folder
    out = tmp_path / "out"
    out.mkdir()
    (out / STAGING_DIR).symlink_to(elsewhere)
    with pytest.raises(SessionError, match="is a link"):
        make_session_folder(out, "demo_S1_T1", 1_700_000_000_000_000_000, _note_name)
    assert (elsewhere / "1-1-0123abcd").is_dir() and sorted(p.name for p in out.iterdir()) == [STAGING_DIR]


def test_verify_accepts_a_good_session(small_session: Path) -> None:
    report = verify_session(small_session)
    assert report.ok, report.problems


def test_verify_catches_changed_and_truncated_files(tmp_path: Path) -> None:
    folder = write_session(tmp_path)
    stream = folder / "streams" / "demo.csv"
    stream.write_text(stream.read_text().replace(",1.50\n", ",1.51\n"))
    problems = verify_session(folder).problems
    assert any("sha256" in p for p in problems)
    lines = stream.read_text().splitlines(keepends=True)
    stream.write_text("".join(lines[:-1]))
    problems = verify_session(folder).problems
    assert any("49 samples" in p or "file has 49" in p for p in problems)


def test_verify_catches_time_going_backwards_and_undeclared_gaps(tmp_path: Path) -> None:
    folder = write_session(tmp_path)
    stream = folder / "streams" / "demo.csv"
    lines = stream.read_text().splitlines(keepends=True)
    lines[10], lines[11] = lines[11], lines[10]
    del lines[20]
    stream.write_text("".join(lines))
    problems = " | ".join(verify_session(folder).problems)
    assert "not strictly increasing" in problems
    assert "backwards" in problems
    assert "the manifest declares 0" in problems


def test_declared_outage_gaps_are_notes_unless_strict(tmp_path: Path) -> None:
    folder = write_session(tmp_path, rows=20, seq_step=2)
    report = verify_session(folder)
    assert report.ok and any("declared" in n for n in report.notes)
    assert not verify_session(folder, strict=True).ok


def test_repair_cuts_torn_line_and_marks_recovered(tmp_path: Path) -> None:
    folder = write_session(tmp_path, rows=30)
    manifest = load_manifest(folder)
    manifest["status"] = "recording"
    write_manifest(folder, manifest)
    stream = folder / "streams" / "demo.csv"
    with open(stream, "a") as fh:
        fh.write("30,17000")  # the kill happened mid-line
    assert not verify_session(folder).ok
    with pytest.raises(SessionError, match="repair"):
        Session.open(folder).read_stream("demo")
    report = repair_session(folder)
    assert report.repaired and report.cut == {"demo": {"bytes": 8, "lines": 1}}
    assert (folder / "logs" / "repair-demo.cut").read_bytes() == b"30,17000"
    assert verify_session(folder).ok
    session = Session.open(folder)
    assert session.status == "recovered" and len(session.read_stream("demo")) == 30
    assert repair_session(folder).repaired is False


def test_find_sessions_walks_a_tree(tmp_path: Path) -> None:
    a = write_session(tmp_path / "day1")
    b = write_session(tmp_path / "day2" / "room")
    assert list(find_sessions(tmp_path)) == sorted([a, b])


def test_the_documented_example_session_verifies_and_matches_the_simulators() -> None:
    from midas_cli.devices.registry import describe_device
    from midas_cli.rig import simulated_rig
    from helpers.cli import REPO

    example = REPO / "sessions_template" / "example_session"
    assert verify_session(example).ok
    session = Session.open(example)
    for name, url in simulated_rig().device_urls().items():
        (spec,) = describe_device(name, url).streams
        assert session.stream_spec(name) == spec, f"{name}: the example's columns no longer match the code"
        assert len(session.read_stream(name)) > 0


def test_frame_labels_round_trip_with_unlabelled_frames(small_session: Path) -> None:
    from midas_cli.session.labels import list_label_sets, read_frame_labels, write_frame_labels

    write_frame_labels(small_session, [0, 1, 2, 5], ["G1", "", "G2", "Idle"], {"taxonomy": "t", "source": "test"})
    got = read_frame_labels(small_session)
    assert got.frames.tolist() == [0, 1, 2, 5] and got.labels.tolist() == ["G1", "", "G2", "Idle"]
    assert got.classes() == ["G1", "G2", "Idle"] and got.meta["taxonomy"] == "t"
    assert "0-based" in got.meta["frame_convention"] and list_label_sets(small_session) == ["gestures"]
    with pytest.raises(SessionError, match="strictly increasing"):
        write_frame_labels(small_session, [2, 1], ["a", "b"], {})
