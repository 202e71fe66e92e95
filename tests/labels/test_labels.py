"""Gesture labels: taxonomies, VIA 3 import (CSV export and project JSON), the frame convention,
overlaps/gaps/clipping, export round trips, JIGSAWS/COMPASS transcriptions and statistics."""

from __future__ import annotations

import json
import os
import statistics
from pathlib import Path

import numpy as np
import pytest

from midas_cli.clock import HostClock
from midas_cli.errors import ConfigError, SessionError
from midas_cli.labels.sessions import ImportOptions, export_labels, import_transcription, import_via, load_recordings
from midas_cli.labels.stats import gesture_stats, transition_heatmap
from midas_cli.labels.taxonomy import load_taxonomy, parse_taxonomy
from midas_cli.session.labels import read_frame_labels
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
from midas_cli.session.writer import SessionMetadata, SessionWriter
from helpers.cli import SHARED_DATA, midas, record_until

FPS = 30.0
VIDEO = StreamSpec("video", "video", (SEQ, T_HOST, Column("t_device_s", "float", "s", 6, clock="device")), FPS)
COMPASS = SHARED_DATA / "compass-suturing-gestures"

# VIA 3 attribute table as the video annotator stores it: a select attribute on temporal segments whose
# options are the taxonomy (option text in the styles annotators use), and a file-level annotator field.
ATTRIBUTES = {
    "1": {"aname": "gesture", "anchor_id": "FILE1_Z2_XY0", "type": 4, "desc": "DESK gesture",
          "options": {"0": "S1", "1": "S2 Align & grasp", "2": "Lift peg", "3": "S4: Transfer peg - Get together",
                      "7": "Idle"}, "default_option_id": ""},
    "2": {"aname": "annotator", "anchor_id": "FILE1_Z0_XY0", "type": 1, "desc": "who annotated",
          "options": {}, "default_option_id": ""},
}
# (metadata id, z, xy, av): S1 0-1 s, S2 0.9-1.5 s (overlaps S1 on frames 27..29), gap 1.5-2 s
# (frames 45..59), S3 2-3.5 s (the 90-frame video ends at 3 s), S4 4-5 s (entirely past the end),
# a still-frame marker, and the file-level annotator entry.
METADATA = [
    ("1_aaaaaa", [0, 1], [], {"1": "0"}),
    ("1_bbbbbb", [0.9, 1.5], [], {"1": "1"}),
    ("1_cccccc", [2, 3.5], [], {"1": "2"}),
    ("1_dddddd", [4, 5], [], {"1": "3"}),
    ("1_eeeeee", [1.2], [], {"1": "0"}),
    ("1_ffffff", [], [], {"2": "Annotator A"}),
]
EXPECTED = ["S1"] * 27 + ["S2"] * 18 + [""] * 15 + ["S3"] * 30


def video_session(root: Path, frames: int = 90, first: int = 0) -> Path:
    """A finished session whose only stream is a 30 fps video frame clock, seq = first..first+frames-1."""
    clock = HostClock.anchored_now()
    writer = SessionWriter.create(root, SessionMetadata("1", "pegtransfer", 1), clock, {"video": {"kind": "test"}},
                                  [VIDEO])
    t0 = clock.now_ns()
    seqs = range(first, first + frames)
    writer.append("video", VIDEO.format_rows([(i, t0 + round(i / FPS * 1e9), i / FPS) for i in seqs]))
    writer.finalize("complete", "test", t0 + round((first + frames) / FPS * 1e9), {})
    return writer.folder


def js(value) -> str:
    """JSON.stringify as VIA (JavaScript) writes it: no spaces, whole floats without '.0'."""
    text = json.dumps(value, separators=(",", ":"))
    return text.replace(".0,", ",").replace(".0]", "]")


def via_csv(path: Path, metadata=METADATA, attributes=ATTRIBUTES) -> Path:
    """A CSV export laid out exactly as VIA 3's export_to_via3_csv writes it."""
    def cell(value) -> str:
        return '"' + js(value).replace('"', '""') + '"'
    lines = ["# Exported using VGG Image Annotator (http://www.robots.ox.ac.uk/~vgg/software/via)",
             "# Notes:",
             "# - spatial_coordinates of [2,10,20,50,80] denotes a rectangle (shape_id=2) of size 50x80 placed at (10,20)",
             "# - temporal coordinate of [1.349,2.741] denotes a temporal segment from time 1.346 sec. to 2.741 sec.",
             "# - temporal coordinate of [4.633] denotes a still video frame at 4.633 sec.",
             '# - metadata of {""1"":""3""} indicates attribute with id "1" set to an attribute option with id "3"',
             '# SHAPE_ID = {"POINT":1,"RECTANGLE":2,"CIRCLE":3,"ELLIPSE":4,"LINE":5,"POLYLINE":6,"POLYGON":7,'
             '"EXTREME_RECTANGLE":8,"EXTREME_CIRCLE":9}',
             '# FLAG_ID = {"RESERVED_FOR_FUTURE":1}',
             f"# ATTRIBUTE = {js(attributes)}",
             "# CSV_HEADER = metadata_id,file_list,flags,temporal_coordinates,spatial_coordinates,metadata"]
    for mid, z, xy, av in metadata:
        lines.append(",".join([f'"{mid}"', cell(["trial1_left.mp4"]), "0", cell(z), cell(xy), cell(av)]))
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def via_json(path: Path, metadata=METADATA) -> Path:
    """A project file as VIA 3's "Save project" writes it."""
    project = {
        "project": {"pid": "__VIA_PROJECT_ID__", "rev": "__VIA_PROJECT_REV_ID__",
                    "rev_timestamp": "__VIA_PROJECT_REV_TIMESTAMP__", "pname": "peg transfer",
                    "creator": "VGG Image Annotator (http://www.robots.ox.ac.uk/~vgg/software/via)",
                    "created": 1718000000000, "vid_list": ["1"]},
        "config": {"file": {"loc_prefix": {"1": "", "2": "", "3": "", "4": ""}},
                   "ui": {"file_content_align": "center", "file_metadata_editor_visible": True,
                          "spatial_metadata_editor_visible": True, "temporal_segment_metadata_editor_visible": True,
                          "spatial_region_label_attribute_id": "", "gtimeline_visible_row_count": "4"}},
        "attribute": ATTRIBUTES,
        "file": {"1": {"fid": "1", "fname": "trial1_left.mp4", "type": 4, "loc": 1, "src": ""}},
        "metadata": {mid: {"vid": "1", "flg": 0, "z": z, "xy": xy, "av": av} for mid, z, xy, av in metadata},
        "view": {"1": {"fid_list": ["1"]}},
    }
    path.write_text(json.dumps(project), encoding="utf-8")
    return path


def labels_of(session: Path, name: str = "gestures") -> list[str]:
    return read_frame_labels(session, name).labels.tolist()


def peg(**kwargs) -> ImportOptions:
    return ImportOptions("peg-transfer", **kwargs)


# --- taxonomies -------------------------------------------------------------------------------------

def test_taxonomies_ship_with_the_papers_classes() -> None:
    peg = load_taxonomy("peg-transfer")
    assert peg.ids == ["S1", "S2", "S3", "S4", "S5", "S6", "S7", "Idle"] and peg.idle == "Idle"
    assert peg.gesture("S5").name == "Transfer peg - Exchange"
    hernia = load_taxonomy("hernia-suturing")
    assert hernia.ids == [f"G{i}" for i in range(1, 9)] and hernia.idle is None
    assert hernia.gesture("G6").name == "Pull Suture"
    assert "fulcrum" in hernia.gesture("G5").main_arm and "long end" in hernia.gesture("G5").support_arm
    assert load_taxonomy("jigsaws-suturing").ids == [f"G{i}" for i in range(1, 12)]


def test_taxonomy_command_lists_and_prints() -> None:
    listing = json.loads(midas("labels", "taxonomy", "--json", check=True).stdout)
    assert {t["name"] for t in listing} == {"peg-transfer", "hernia-suturing", "jigsaws-suturing"}
    table = midas("labels", "taxonomy", "hernia-suturing", check=True).stdout
    assert "Square Knot and Cinch" in table and "Main arm" in table
    with pytest.raises(ConfigError, match="unknown taxonomy 'knitting'"):
        load_taxonomy("knitting")


def test_taxonomy_validation_refuses_duplicates_and_a_foreign_idle() -> None:
    gestures = [{"id": "A", "name": "a"}, {"id": "A", "name": "b"}]
    with pytest.raises(ConfigError, match="duplicate gesture id"):
        parse_taxonomy({"name": "x", "gestures": gestures}, "test")
    with pytest.raises(ConfigError, match="idle class 'Rest'"):
        parse_taxonomy({"name": "x", "idle": "Rest", "gestures": gestures[:1]}, "test")


# --- VIA import -------------------------------------------------------------------------------------

def test_via_csv_export_imports_with_overlap_gap_and_clipping_reported(tmp_path: Path) -> None:
    session = video_session(tmp_path)
    result = midas("labels", "import-via", str(via_csv(tmp_path / "export.csv")), str(session),
                   "--taxonomy", "peg-transfer", check=True)
    assert labels_of(session) == EXPECTED
    text = result.stdout
    assert "overlap: 1_aaaaaa and 1_bbbbbb (S1/S2) share frames 27..29 (3)" in text
    assert "gap: frames 45..59 (15, between segments): left unlabelled" in text
    assert "clipped: 1_cccccc (S3) lost 15 frame(s) at its end" in text
    assert "dropped: 1_dddddd (S4, frames 120..149): after the video's last frame" in text
    assert "skipped: 1_eeeeee: still-frame marker" in text
    meta = read_frame_labels(session).meta
    assert meta["taxonomy"] == "peg-transfer" and meta["source"]["kind"] == "via-csv"
    assert meta["source"]["annotator"] == "Annotator A" and len(meta["source"]["sha256"]) == 64
    assert meta["frame_convention"].startswith("0-based")


def test_via_project_json_gives_the_same_labels_and_gaps_can_be_idle(tmp_path: Path) -> None:
    session = video_session(tmp_path)
    report = import_via(via_json(tmp_path / "project.json"), session, peg(gaps="idle")).to_json()
    assert labels_of(session) == [label or "Idle" for label in EXPECTED]
    assert report["source"]["kind"] == "via-json" and report["source"]["annotator"] == "Annotator A"
    assert report["report"]["gap_mode"] == "idle" and report["report"]["frame_counts"]["Idle"] == 15


def test_overlap_rule_earlier_and_error(tmp_path: Path) -> None:
    session = video_session(tmp_path)
    export = via_csv(tmp_path / "export.csv")
    import_via(export, session, peg(overlap="earlier"))
    assert labels_of(session)[:45] == ["S1"] * 30 + ["S2"] * 15
    with pytest.raises(SessionError, match="share frames 27..29"):
        import_via(export, session, peg(overlap="error", name="strict"))


def test_frame_index_convention_is_zero_based_without_a_shift(tmp_path: Path) -> None:
    """[1.0 s, 2.0 s) at 30 fps is frames 30..59: frame 30 is the 31st frame, starting at exactly 1.0 s.
    A 0-based/1-based mix-up (the original pipeline's) would label 31..60."""
    session = video_session(tmp_path)
    export = via_csv(tmp_path / "one.csv", [("1_xxxxxx", [1, 2], [], {"1": "0"})])
    import_via(export, session, peg())
    labels = read_frame_labels(session)
    on = labels.frames[labels.labels == "S1"]
    assert (on.min(), on.max(), len(on)) == (30, 59, 30)
    transcription = tmp_path / "t.txt"
    transcription.write_bytes(b"31 60 G1 \r\n")
    import_transcription(transcription, session, ImportOptions("jigsaws-suturing", name="jig"))
    jig = read_frame_labels(session, "jig")
    assert jig.frames[jig.labels == "G1"].tolist() == list(range(30, 60))


def test_a_file_without_gesture_segments_is_refused(tmp_path: Path) -> None:
    session = video_session(tmp_path)
    export = via_csv(tmp_path / "markers.csv", [("1_xxxxxx", [0.5], [], {"1": "0"})])
    with pytest.raises(SessionError, match="no gesture segments.*still-frame marker"):
        import_via(export, session, peg())


def test_unknown_option_id_is_an_error_naming_it(tmp_path: Path) -> None:
    session = video_session(tmp_path)
    export = via_csv(tmp_path / "bad.csv", [("1_xxxxxx", [0, 1], [], {"1": "9"})])
    result = midas("labels", "import-via", str(export), str(session), "--taxonomy", "peg-transfer")
    assert result.returncode == 2
    assert "unknown option id '9'" in result.stderr and "1_xxxxxx" in result.stderr
    assert not (session / "labels").exists()


def test_option_text_outside_the_taxonomy_and_existing_sets_are_refused(tmp_path: Path) -> None:
    session = video_session(tmp_path)
    export = via_csv(tmp_path / "export.csv")
    with pytest.raises(ConfigError, match="names no gesture of taxonomy 'hernia-suturing'"):
        import_via(export, session, ImportOptions("hernia-suturing"))
    import_via(export, session, peg())
    with pytest.raises(SessionError, match="--force"):
        import_via(export, session, peg())
    import_via(export, session, peg(force=True))


# --- export round trips -----------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["via", "via-csv"])
def test_export_then_import_is_identity(tmp_path: Path, fmt: str) -> None:
    session = video_session(tmp_path)
    import_via(via_json(tmp_path / "p.json"), session, peg())
    exported = tmp_path / f"round.{fmt}"
    if fmt == "via":  # through the CLI once, the other format through the library
        midas("labels", "export", str(session), "--format", fmt, "--out", str(exported), check=True)
    else:
        exported.write_text(export_labels(session, fmt))
    import_via(exported, session, peg(name="back"))
    original, back = read_frame_labels(session), read_frame_labels(session, "back")
    assert np.array_equal(original.frames, back.frames)
    assert original.labels.tolist() == back.labels.tolist() == EXPECTED
    assert back.meta["report"]["overlaps"] == [] and back.meta["report"]["clipped"] == []


def test_plain_csv_export_lists_segments_in_frames_and_seconds(tmp_path: Path) -> None:
    session = video_session(tmp_path)
    import_via(via_csv(tmp_path / "e.csv"), session, peg())
    rows = export_labels(session, "csv").splitlines()
    assert rows == ["gesture,start_frame,end_frame,frames,start_s,end_s,duration_s",
                    "S1,0,26,27,0.00000,0.90000,0.90000",
                    "S2,27,44,18,0.90000,1.50000,0.60000",
                    "S3,60,89,30,2.00000,3.00000,1.00000"]


def test_a_recorded_simulated_session_is_labelled_on_its_own_frames(tmp_path: Path) -> None:
    """The simulated recorder's video stream starts at a frame > 0 (its timecode is seq / 30): a segment
    over 0..100 s is clipped at both ends, and labels land on the recorded frame indices."""
    result = record_until(tmp_path / "rec", ["--simulate", "--no-tui", "--subject", "1", "--task", "t", "--trial", "1"],
                          {"video": 10})
    assert result.returncode == 0, result.stderr
    session = next((tmp_path / "rec").iterdir())
    export = via_csv(tmp_path / "e.csv", [("1_xxxxxx", [0, 100], [], {"1": "7"})])
    report = import_via(export, session, peg()).report.to_json()
    labels = read_frame_labels(session)
    assert set(labels.labels.tolist()) == {"Idle"} and labels.frames[0] > 0
    assert [c["side"] for c in report["clipped"]] == ["both"]
    assert report["clipped"][0]["frames_cut"] == labels.frames[0] + 3000 - 1 - labels.frames[-1]


# --- transcriptions and statistics ------------------------------------------------------------------

def test_transcription_import_reads_crlf_and_rejects_unknown_gestures(tmp_path: Path) -> None:
    session = video_session(tmp_path)
    good = tmp_path / "Suturing_S01_T01.txt"
    good.write_bytes(b"11 40 G1 \r\n41 70 G5 \r\n71 95 G8 \r\n")
    text = midas("labels", "import-transcription", str(good), str(session), check=True).stdout
    assert labels_of(session) == [""] * 10 + ["G1"] * 30 + ["G5"] * 30 + ["G8"] * 20
    assert "gap: frames 0..9 (10, before the first segment)" in text
    assert "clipped: Suturing_S01_T01.txt:3 (G8) lost 5 frame(s) at its end" in text
    assert read_frame_labels(session).meta["source"]["index_base"] == 1
    bad = tmp_path / "bad.txt"
    bad.write_text("1 10 G99\n")
    with pytest.raises(ConfigError, match="G99"):
        import_transcription(bad, session, ImportOptions("jigsaws-suturing", name="bad"))


def test_stats_counts_durations_and_transitions(tmp_path: Path) -> None:
    folder = tmp_path / "gestures"
    folder.mkdir()
    (folder / "a.txt").write_bytes(b"1 30 G1 \r\n31 90 G2 \r\n91 120 G1 \r\n")
    (folder / "b.txt").write_bytes(b"5 64 G2 \r\n65 94 G3 \r\n")
    plot = tmp_path / "transitions.png"
    data = json.loads(midas("labels", "stats", str(folder), "--json", "--plot", str(plot), check=True).stdout)
    rows = {r["id"]: r for r in data["gestures"]}
    assert data["classes"] == 3 and data["samples"] == 5 and data["recordings"] == 2
    assert rows["G1"]["samples"] == 2 and rows["G1"]["mean_s"] == 1.0 and rows["G1"]["std_s"] == 0.0
    assert rows["G2"]["mean_s"] == 2.0 and rows["G3"]["std_s"] is None
    assert data["transitions"] == {"labels": ["G1", "G2", "G3"], "counts": [[0, 1, 0], [1, 0, 1], [0, 0, 0]]}
    old = midas("labels", "stats", str(folder), "--fps", "15", "--json", check=True)  # the old name of --frame-rate
    assert {r["id"]: r["mean_s"] for r in json.loads(old.stdout)["gestures"]}["G2"] == 4.0
    assert "midas: warning: --fps is now --frame-rate" in old.stderr
    without = gesture_stats(load_recordings([folder])[0], exclude=["G2"])
    assert without.classes == ["G1", "G3"] and without.transitions.tolist() == [[1, 0], [0, 0]]
    import cv2

    image = cv2.imread(str(plot))
    assert image is not None and image.shape[0] > 100
    with pytest.raises(ConfigError, match="name it .png"):  # OpenCV has no encoder for .csv: it raised (exit 1)
        transition_heatmap(without, tmp_path / "transitions.csv")
    assert not (tmp_path / "transitions.csv").exists()


def test_stats_on_a_session_uses_its_taxonomy_and_frame_rate(tmp_path: Path) -> None:
    session = video_session(tmp_path)
    import_via(via_csv(tmp_path / "e.csv"), session, peg())
    table = midas("labels", "stats", str(session), check=True).stdout
    assert "Align & grasp" in table and "0.60 ± —" in table
    recordings, taxonomy = load_recordings([session])
    assert taxonomy == "peg-transfer"
    data = gesture_stats(recordings, load_taxonomy(taxonomy)).to_json()
    assert [(r["id"], r["samples"], r["mean_s"]) for r in data["gestures"]] == [("S1", 1, 0.9), ("S2", 1, 0.6),
                                                                                 ("S3", 1, 1.0)]
    meta_path = next((session / "labels").glob("*.json"))  # a label set made with a taxonomy file of its own
    meta = json.loads(meta_path.read_text())
    meta_path.write_text(json.dumps({**meta, "taxonomy": "our-own\x1b[2J"}))
    own = midas("labels", "stats", str(session))  # only its name was recorded: the gestures as they come, warned
    assert own.returncode == 0 and "S2" in own.stdout and "Align & grasp" not in own.stdout
    assert "'our-own\\x1b[2J'" in own.stderr and "\x1b" not in own.stderr and "does not ship" in own.stderr


@pytest.mark.shared_data("compass-suturing-gestures")
def test_stats_on_the_real_compass_suturing_transcriptions() -> None:
    files = sorted(COMPASS.glob("*.txt"))
    durations: dict[str, list[float]] = {}
    for file in files:
        for line in file.read_text().split("\n"):
            if line.strip():
                start, end, gesture = line.split()
                durations.setdefault(gesture, []).append((int(end) - int(start) + 1) / 30)
    data = json.loads(midas("labels", "stats", str(COMPASS), "--taxonomy", "jigsaws-suturing", "--json",
                            check=True).stdout)
    assert len(files) == 34 and data["recordings"] == 34
    assert data["classes"] == 10 == len(durations)
    assert "G7" not in {r["id"] for r in data["gestures"]}
    for row in data["gestures"]:
        expected = durations[row["id"]]
        assert row["samples"] == len(expected)
        assert row["mean_s"] == pytest.approx(statistics.mean(expected), abs=1e-3)
        assert row["std_s"] == pytest.approx(statistics.stdev(expected), abs=1e-3)
    assert data["total_min"] == pytest.approx(sum(map(sum, durations.values())) / 60, abs=1e-2)


@pytest.mark.parametrize("kind", ["folder", "fifo"])
def test_a_label_set_file_that_is_no_regular_file_is_named_as_such(tmp_path: Path, kind: str) -> None:
    """Not 'no label set gestures (label sets: gestures)': the file is there, but nothing to read."""
    csv = tmp_path / "labels" / "gestures.csv"
    csv.parent.mkdir()
    if kind == "folder":
        csv.mkdir()
    else:
        os.mkfifo(csv)  # nobody writes to it: a read would hang
    with pytest.raises(SessionError, match=f"{csv}: not a regular file"):
        read_frame_labels(tmp_path)
