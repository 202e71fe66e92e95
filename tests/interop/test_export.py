"""`midas export --format mcap|parquet|xdf`: round trips through mcap's reader, Foxglove's own readers (node),
pandas.read_parquet and pyxdf."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from midas_cli.session.labels import read_frame_labels
from midas_cli.session.reader import Session
from helpers.cli import SHARED_DATA, midas
from helpers.foxglove import read_with_foxglove

SAMPLE_NAME = "midas-dcs-sample/trakt_Strakt_T1_2024-07-05"


def _export(session: Path, out: Path) -> None:
    result = midas("export", str(session), "--format", "mcap,parquet", "--format", "xdf", "--out", str(out))
    assert result.returncode == 0, result.stderr
    stem = Session.open(session).manifest["session_id"]
    assert result.stdout.split() == [str(out / f"{stem}.mcap"), str(out / stem), str(out / f"{stem}.xdf")]


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("export")
    made = midas("simulate", "dataset", "--trials", "1", "--max-seconds", "5", "--out", str(root / "sim"), check=True)
    session = Path(made.stdout.split()[-1])
    midas("align", str(session), check=True)
    _export(session, root / "out")
    return session, root / "out"


def _check_mcap(session_path: Path, out: Path) -> None:
    """Python's mcap reader: every row at its t_host_ns, single-typed fields, missing values left out."""
    from mcap.reader import make_reader

    session = Session.open(session_path)
    with open(out / f"{session.manifest['session_id']}.mcap", "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        counts = {topics_id.topic: summary.statistics.channel_message_counts.get(cid, 0)
                  for cid, topics_id in summary.channels.items()}
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        first: dict[str, list] = {}
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            first.setdefault(channel.topic, []).append((message.log_time, message.data))
    assert json.loads(metadata["midas.manifest"]["manifest.json"]) == session.manifest
    for name in session.stream_names:
        frame = session.read_stream(name)
        assert counts[f"/{name}"] == len(frame)
        times = np.array([t for t, _ in first[f"/{name}"]], dtype=np.int64)
        assert np.array_equal(times, frame["t_host_ns"].to_numpy())  # log_time = t_host_ns, exactly
        if name == "events":
            continue  # foxglove.Log (protobuf): read by test_mcap_opens_with_foxglove_readers
        schema = json.loads(summary.schemas[topics[f"/{name}"].schema_id].data)
        assert {k: v["unit"] for k, v in schema["properties"].items()} == \
            {c.name: c.unit for c in session.stream_spec(name).columns}
        assert all(isinstance(v["type"], str) for v in schema["properties"].values())  # one type per field
        for at in (0, -1):
            row = json.loads(first[f"/{name}"][at][1])
            expected = {k: v for k, v in frame.iloc[at].to_dict().items() if not pd.isna(v)}
            assert row == pytest.approx(expected)
    for name in (p.stem for p in (session_path / "labels").glob("*.csv")):
        labels = read_frame_labels(session_path, name)
        assert counts[f"/labels/{name}"] == len(labels.frames)
        assert [json.loads(d)["label"] for _, d in first[f"/labels/{name}"]] == labels.labels.tolist()


def _check_parquet(session_path: Path, out: Path) -> None:
    session = Session.open(session_path)
    folder = out / session.manifest["session_id"]
    metadata = session.manifest["metadata"]
    for name in session.stream_names:
        whole = pd.read_parquet(folder / f"{name}.parquet")
        back = whole[[c.name for c in session.stream_spec(name).columns]]
        pd.testing.assert_frame_equal(back, session.read_stream(name), check_exact=True)
        assert set(whole["session_id"]) <= {session.manifest["session_id"]}  # every row names its session
        assert set(whole["task"]) <= {metadata.get("task")} and set(whole["trial"]) <= {metadata.get("trial")}
        raw = pd.read_csv(session.stream_path(name), keep_default_na=False, na_values=[""])  # the CSV as text -> numbers
        assert np.array_equal(back.to_numpy(np.float64, na_value=np.nan), raw.to_numpy(np.float64), equal_nan=True)
        assert back["t_host_ns"].dtype == np.int64 and back["t_host_ns"].equals(raw["t_host_ns"])
        import pyarrow.parquet as pq
        meta = pq.read_schema(folder / f"{name}.parquet").metadata
        assert json.loads(meta[b"midas.units"]) == {c.name: c.unit for c in session.stream_spec(name).columns}
        assert json.loads(meta[b"midas.manifest"]) == session.manifest
    for name in (p.stem for p in (session_path / "labels").glob("*.csv")):
        back = pd.read_parquet(folder / f"labels_{name}.parquet")
        csv = pd.read_csv(session_path / "labels" / f"{name}.csv", dtype={"label": str}, keep_default_na=False)
        pd.testing.assert_frame_equal(back[["frame", "label"]], csv, check_dtype=False)


def _check_xdf(session_path: Path, out: Path) -> None:
    import pyxdf

    from midas_cli.interop.lsl_replay import describe, plan_replay

    session = Session.open(session_path)
    path = out / f"{session.manifest['session_id']}.xdf"
    replayed = {d["name"]: d for d in describe(plan_replay(session_path, delay_s=0.0))}
    for sync in (False, True):
        streams, header = pyxdf.load_xdf(str(path), synchronize_clocks=sync, dejitter_timestamps=False)
        by_name = {s["info"]["name"][0]: s for s in streams}
        for name, outlet in replayed.items():  # one scheme: what LabRecorder would have recorded from replay
            info = by_name[name]["info"]
            assert info["source_id"] == [outlet["source_id"]] == [f"midas:{session_path.name}:{name}"]
            assert info["type"] == [outlet["type"]] and int(info["channel_count"][0]) == outlet["channels"]
        if "emht" in replayed:
            assert by_name["emht"]["info"]["type"] == ["MoCap"]
        for name in session.stream_names:
            frame, spec, stream = session.read_stream(name), session.stream_spec(name), by_name[name]
            channels = stream["info"]["desc"][0]["channels"][0]["channel"]
            columns = [c for c in spec.columns if c.name != "t_host_ns"]
            assert int(stream["info"]["channel_count"][0]) == len(columns)
            assert [c["label"][0] for c in channels] == [c.name for c in columns]
            assert [(c["unit"] or [""])[0] or "" for c in channels] == [c.unit for c in columns]
            assert float(stream["info"]["nominal_srate"][0]) == (spec.nominal_rate_hz or 0)
            assert stream["time_series"].shape == (len(frame), len(columns))
            assert np.abs(stream["time_stamps"] - frame["t_host_ns"].to_numpy() / 1e9).max(initial=0) < 1e-6
            assert np.array_equal(stream["time_series"], frame[[c.name for c in columns]].to_numpy(
                np.float64, na_value=np.nan), equal_nan=True)
            assert stream["clock_values"] and not any(stream["clock_values"])  # one host clock: offsets 0


def test_simulated_session_round_trips(simulated: tuple[Path, Path]) -> None:
    session, out = simulated
    _check_mcap(session, out)
    _check_parquet(session, out)
    aligned = pd.read_parquet(out / Session.open(session).manifest["session_id"] / "aligned.parquet")
    assert len(aligned) > 0 and aligned["t_host_ns"].dtype == np.int64
    _check_xdf(session, out)


@pytest.mark.slow
def test_small_pieces_give_the_same_files(simulated: tuple[Path, Path], tmp_path: Path, monkeypatch) -> None:
    """Streams are read a piece at a time: many small pieces give the same values."""
    from midas_cli.interop.export import export_session
    from midas_cli.session import reader

    monkeypatch.setattr(reader, "CHUNK_BYTES", 4096)
    monkeypatch.setattr(reader.Session.iter_stream, "__defaults__", (4096, False))
    session, _ = simulated
    export_session(session, ["parquet", "xdf"], tmp_path)
    _check_parquet(session, tmp_path)
    _check_xdf(session, tmp_path)
    import pyarrow.parquet as pq
    stem = Session.open(session).manifest["session_id"]
    assert pq.ParquetFile(tmp_path / stem / "emht.parquet").num_row_groups > 10


def test_bad_format_is_a_usage_error(simulated: tuple[Path, Path], tmp_path: Path) -> None:
    result = midas("export", str(simulated[0]), "--format", "hdf5", "--out", str(tmp_path))
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1 and "hdf5" in result.stderr
    assert not any(tmp_path.iterdir())


def test_out_inside_a_session_is_refused(simulated: tuple[Path, Path]) -> None:
    result = midas("export", str(simulated[0]), "--format", "xdf", "--out", str(simulated[0] / "streams"))
    assert result.returncode == 2, result.stderr


@pytest.mark.shared_data(SAMPLE_NAME)
def test_imported_original_session_round_trips(tmp_path: Path) -> None:
    made = midas("import", "midas-dcs", str(SHARED_DATA / SAMPLE_NAME), "--out", str(tmp_path / "in"), check=True)
    session = Path(made.stdout.split()[-1])
    _export(session, tmp_path / "out")
    _check_mcap(session, tmp_path / "out")
    _check_parquet(session, tmp_path / "out")
    _check_xdf(session, tmp_path / "out")


def _session_with_markers(root: Path, subject: str, trial: int, markers: list[str]) -> Path:
    """A small session: a float stream with a nullable int column and the events stream (maybe empty)."""
    from midas_cli.clock import HostClock
    from midas_cli.record.markers import events_spec
    from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
    from midas_cli.session.writer import SessionMetadata, SessionWriter

    force = StreamSpec("force", "fps", (SEQ, T_HOST, Column("ch0", "float", "V"), Column("state", "int")), 100.0)
    clock = HostClock.anchored_now()
    writer = SessionWriter.create(root, SessionMetadata(subject, "knot", trial), clock, {}, [force, events_spec()])
    t0 = clock.now_ns()
    writer.append("force", force.format_rows([(k, t0 + k * 10_000_000, 0.5 * k, None if k % 2 else k)
                                              for k in range(5)]))
    if markers:
        writer.append("events", events_spec().format_rows([(k, t0 + k, text, "mark")
                                                           for k, text in enumerate(markers)]))
    writer.finalize("complete", "test", t0 + 60_000_000, {})
    return writer.folder


def test_parquet_of_many_sessions_reads_as_one_table_in_duckdb(tmp_path: Path) -> None:
    """Column types come from the declared columns, not the content: a session without markers still
    types `text` as a string, so DuckDB reads every session's events at once; rows name their session."""
    import duckdb

    sessions = [_session_with_markers(tmp_path / "in", "7", 1, ["needle in", "knot"]),
                _session_with_markers(tmp_path / "in", "8", 2, [])]
    out = tmp_path / "out"
    assert midas("export", *map(str, sessions), "--format", "parquet", "--out", str(out)).returncode == 0
    events = duckdb.sql(f"select subject, trial, text from read_parquet('{out}/*/events.parquet') "
                        "order by subject, seq").fetchall()
    assert events == [("7", 1, "needle in"), ("7", 1, "knot")]
    counts = duckdb.sql(f"select session_id, count(*), count(state), sum(ch0) from read_parquet("
                        f"'{out}/*/force.parquet') group by session_id order by session_id").fetchall()
    assert counts == sorted((Session.open(s).manifest["session_id"], 5, 3, 5.0) for s in sessions)
    types = dict(duckdb.sql(f"select column_name, column_type from (describe select * from read_parquet("
                            f"'{out}/*/events.parquet'))").fetchall())
    assert types["text"] == types["source"] == types["subject"] == "VARCHAR" and types["trial"] == "BIGINT"
    import pyarrow.parquet as pq
    without_markers = pq.read_schema(out / Session.open(sessions[1]).manifest["session_id"] / "events.parquet")
    assert [str(without_markers.field(c).type) for c in ("seq", "text", "source")] == ["int64", "string", "string"]


def test_mcap_opens_with_foxglove_readers(simulated: tuple[Path, Path]) -> None:
    """Foxglove's packages decode every message against its schema; EmHT sensors are transforms in metres
    and quaternions from the recorded angles, in named frames."""
    from midas_cli.geometry import quaternions_from_angles

    session_path, out = simulated
    session = Session.open(session_path)
    read = read_with_foxglove(out / f"{session.manifest['session_id']}.mcap")
    topics = read["topics"]
    assert {"midas.manifest", "midas.labels.gestures"} <= set(read["metadata"])
    emht = session.read_stream("emht")
    for name in session.stream_names:
        assert topics[f"/{name}"]["count"] == len(session.read_stream(name))
        assert topics[f"/{name}"]["first"]["seq"] == int(session.read_stream(name)["seq"].iloc[0])
    transforms = topics["/emht/transforms"]
    assert transforms["schema"] == "foxglove.FrameTransforms" and transforms["count"] == len(emht)
    last = transforms["last"]["transforms"]
    assert [t["child_frame_id"] for t in last] == ["emht/s1", "emht/s2", "emht/s3", "emht/s4"]
    assert {t["parent_frame_id"] for t in last} == {"emht_transmitter"}
    row = emht.iloc[-1]
    for k, transform in enumerate(last, start=1):
        translation = [transform["translation"][a] for a in "xyz"]
        assert translation == pytest.approx([row[f"s{k}_{a}_mm"] / 1000 for a in "xyz"])
        expected = quaternions_from_angles(np.array([[row[f"s{k}_{a}_deg"] for a in ("azimuth", "elevation", "roll")]]))
        assert [transform["rotation"][a] for a in "xyzw"] == pytest.approx(expected[0].tolist())
    stamp = last[0]["timestamp"]
    assert int(stamp["seconds"]) * 10**9 + stamp["nanos"] == int(emht["t_host_ns"].iloc[-1])
    labels = topics["/labels/gestures"]
    assert labels["first"] == {"label": read_frame_labels(session_path, "gestures").labels[0], "frame": 0}


def test_mcap_markers_are_foxglove_logs_and_missing_values_are_left_out(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    from midas_cli.interop.mcap_export import write_mcap

    session = Session.open(_session_with_markers(tmp_path / "in", "7", 1, ["needle in", "knot"]))
    write_mcap(session, tmp_path / "s.mcap")
    topics = read_with_foxglove(tmp_path / "s.mcap")["topics"]
    events = topics["/events"]
    assert events["schema"] == "foxglove.Log" and events["count"] == 2
    assert (events["first"]["message"], events["first"]["name"], events["last"]["message"]) == ("needle in", "mark", "knot")
    assert events["first"]["level"] == 2  # INFO
    with open(tmp_path / "s.mcap", "rb") as fh:
        rows = [json.loads(m.data) for _, c, m in make_reader(fh).iter_messages(topics=["/force"])]
    assert [row.get("state") for row in rows] == [0, None, 2, None, 4]
    assert "state" not in rows[1] and rows[1]["ch0"] == 0.5  # left out, never null


def _session_with_frames(root: Path, colours: list[tuple[int, int, int]]) -> Path:
    """A session with a simulated RGB-D camera's frame stream and its MJPG file: one solid colour per frame."""
    import cv2

    from midas_cli.clock import HostClock
    from midas_cli.devices.registry import describe_device
    from midas_cli.session.writer import SessionMetadata, SessionWriter

    spec = next(s for s in describe_device("rgbd", "sim://rgbd?rate=8", 0).streams if s.name == "rgbd")
    clock = HostClock.anchored_now()
    writer = SessionWriter.create(root, SessionMetadata("1", "rgbd", 1), clock, {}, [spec])
    (writer.folder / "video").mkdir(exist_ok=True)
    video = cv2.VideoWriter(str(writer.folder / "video" / "rgbd_000.mkv"), cv2.VideoWriter_fourcc(*"MJPG"), 8, (64, 32))
    for colour in colours:
        video.write(np.full((32, 64, 3), colour, dtype=np.uint8))
    video.release()
    t0 = clock.now_ns()
    writer.append("rgbd", spec.format_rows([(k, t0 + k * 125_000_000, k * 125_000_000, 0, k) for k in range(len(colours))]))
    writer.finalize("complete", "test", t0 + 10**9, {})
    return writer.folder


def test_mcap_with_video_has_the_rgbd_frames_as_images(tmp_path: Path) -> None:
    import base64

    import cv2

    from midas_cli.interop.mcap_export import write_mcap

    colours = [(0, 0, 250), (0, 250, 0), (250, 0, 0)]  # BGR
    session = Session.open(_session_with_frames(tmp_path / "in", colours))
    assert "/rgbd/image" not in write_mcap(session, tmp_path / "plain.mcap")["messages"]  # only on request
    write_mcap(session, tmp_path / "s.mcap", with_video=True)
    images = read_with_foxglove(tmp_path / "s.mcap")["topics"]["/rgbd/image"]
    assert images["schema"] == "foxglove.CompressedImage" and images["count"] == len(colours)
    rows = session.read_stream("rgbd")
    for message, colour, t_ns in ((images["first"], colours[0], rows["t_host_ns"].iloc[0]),
                                  (images["last"], colours[-1], rows["t_host_ns"].iloc[-1])):
        assert message["format"] == "jpeg" and message["frame_id"] == "rgbd"
        assert int(message["timestamp"]["seconds"]) * 10**9 + message["timestamp"]["nanos"] == int(t_ns)
        image = cv2.imdecode(np.frombuffer(base64.b64decode(message["data"]), np.uint8), cv2.IMREAD_COLOR)
        assert image.shape == (32, 64, 3) and np.abs(image.mean(axis=(0, 1)) - colour).max() < 12


def test_only_six_dof_sensors_become_transforms() -> None:
    from midas_cli.analysis.kinematics_schema import kinematics_spec
    from midas_cli.devices.emht_layout import emht_stream
    from midas_cli.analysis.handkp import handkp_spec
    from midas_cli.interop.foxglove_topics import sensor_columns

    sensors = sensor_columns(emht_stream("emht", 2, 240.0))
    assert [(s.name, s.parent_frame) for s in sensors] == [("s1", "emht_transmitter"), ("s2", "emht_transmitter")]
    assert sensors[1].orientation == ("s2_azimuth_deg", "s2_elevation_deg", "s2_roll_deg")
    arms = sensor_columns(kinematics_spec("psm"))
    assert [(s.name, s.parent_frame) for s in arms] == [("left", "psm"), ("right", "psm")]
    assert arms[1].orientation == ("right_qx", "right_qy", "right_qz", "right_qw")
    assert sensor_columns(handkp_spec("handkp", 30.0)) == []  # positions without orientation: a time series only


def test_mcap_robot_arms_are_transforms_foxglove_reads(tmp_path: Path) -> None:
    """The robot arms (``mtm``/``psm`` kinematics: mm and a quaternion) are frames ``psm/left``,
    ``psm/right`` in ``psm`` for the 3-D panel; a zero or missing quaternion leaves that arm out."""
    from midas_cli.analysis.kinematics_schema import kinematics_spec, side_columns
    from midas_cli.clock import HostClock
    from midas_cli.interop.mcap_export import write_mcap
    from midas_cli.session.writer import SessionMetadata, SessionWriter

    spec = kinematics_spec("psm")
    clock = HostClock.anchored_now()
    writer = SessionWriter.create(tmp_path / "in", SessionMetadata("1", "pegs", 1), clock, {}, [spec])
    t0 = clock.now_ns()
    left = [10.0, -20.0, 30.0, 0.0, 0.0, 0.6, 0.8, 0.0, 0.0, 0.0, 5.0]  # quaternion already unit
    right = [1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 5.0]  # |q| = 2: sent normalised
    rows = [(0, t0, 0.0, *left, *right, 0), (1, t0 + 10_000_000, 0.01, *left, *right[:3], 0.0, 0.0, 0.0, 0.0,
                                               *right[7:], 0)]
    writer.append("psm", spec.format_rows(rows))
    writer.finalize("complete", "test", t0 + 10**9, {})
    write_mcap(Session.open(writer.folder), tmp_path / "s.mcap")
    transforms = read_with_foxglove(tmp_path / "s.mcap")["topics"]["/psm/transforms"]
    assert transforms["schema"] == "foxglove.FrameTransforms" and transforms["count"] == 2
    first, last = transforms["first"]["transforms"], transforms["last"]["transforms"]
    assert [(t["parent_frame_id"], t["child_frame_id"]) for t in first] == [("psm", "psm/left"), ("psm", "psm/right")]
    assert [first[0]["translation"][a] for a in "xyz"] == pytest.approx([0.01, -0.02, 0.03])
    assert [first[0]["rotation"][a] for a in "xyzw"] == pytest.approx([0.0, 0.0, 0.6, 0.8])
    assert [first[1]["rotation"][a] for a in "xyzw"] == pytest.approx([0.0, 0.0, 0.0, 1.0])
    assert [t["child_frame_id"] for t in last] == ["psm/left"]  # the right arm's zero quaternion: left out
    assert len(side_columns("left")) == len(left)


def _session_with_console_video(root: Path, colours: list[tuple[int, int, int]]) -> Path:
    """A session with a 30 fps frame clock (`video` stream) and its recording in video/ (MJPG, not H.264:
    the export must re-encode), one solid colour per frame."""
    import cv2

    from midas_cli.clock import HostClock
    from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
    from midas_cli.session.writer import SessionMetadata, SessionWriter

    spec = StreamSpec("video", "video", (SEQ, T_HOST, Column("t_device_s", "float", "s", 6, clock="device")), 30.0)
    clock = HostClock.anchored_now()
    writer = SessionWriter.create(root, SessionMetadata("1", "console", 1), clock, {"video": {"kind": "video"}}, [spec])
    (writer.folder / "video").mkdir(exist_ok=True)
    video = cv2.VideoWriter(str(writer.folder / "video" / "console.mkv"), cv2.VideoWriter_fourcc(*"MJPG"), 30, (64, 48))
    for colour in colours:
        video.write(np.full((48, 64, 3), colour, dtype=np.uint8))
    video.release()
    t0 = clock.now_ns()
    writer.append("video", spec.format_rows([(k, t0 + k * 33_333_333, k / 30) for k in range(len(colours))]))
    writer.finalize("complete", "test", t0 + 10**9, {})
    return writer.folder


def test_mcap_with_video_has_the_console_recording_as_h264_foxglove_plays(tmp_path: Path) -> None:
    """One CompressedVideo message per frame at the frame clock's time; a key frame decodes alone (Annex B
    with its SPS), read back by Foxglove's packages and decoded by OpenCV's FFmpeg."""
    import base64

    import cv2

    from midas_cli.interop.mcap_export import write_mcap

    colours = [(0, 0, 250)] * 20 + [(0, 250, 0)] * 20 + [(250, 0, 0)] * 5  # BGR, 45 frames
    session = Session.open(_session_with_console_video(tmp_path / "in", colours))
    assert write_mcap(session, tmp_path / "s.mcap", with_video=True)["messages"]["/video/h264"] == len(colours)
    video = read_with_foxglove(tmp_path / "s.mcap")["topics"]["/video/h264"]
    assert video["schema"] == "foxglove.CompressedVideo" and video["count"] == len(colours)
    rows = session.read_stream("video")
    for message, t_ns in ((video["first"], rows["t_host_ns"].iloc[0]), (video["last"], rows["t_host_ns"].iloc[-1])):
        assert message["format"] == "h264" and message["frame_id"] == "endoscope"
        assert int(message["timestamp"]["seconds"]) * 10**9 + message["timestamp"]["nanos"] == int(t_ns)
    first = tmp_path / "first.h264"
    first.write_bytes(base64.b64decode(video["first"]["data"]))
    capture = cv2.VideoCapture(str(first))
    ok, image = capture.read()
    capture.release()
    assert ok and image.shape == (48, 64, 3) and np.abs(image.mean(axis=(0, 1)) - colours[0]).max() < 12


def _session_with_gestures(root: Path, marker: str) -> Path:
    """A session with a gestures_live-shaped stream: two text columns, the flickering class and the
    decoded one; ``marker`` names the one a marker stream sends."""
    from midas_cli.clock import HostClock
    from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
    from midas_cli.session.writer import SessionMetadata, SessionWriter

    spec = StreamSpec("gestures_live", "recognition", (SEQ, T_HOST, Column("class", "text"), Column("probability", "float"),
                                                       Column("decoded", "text")), 10.0, marker=marker)
    clock = HostClock.anchored_now()
    writer = SessionWriter.create(root, SessionMetadata("7", "knot", 1), clock, {}, [spec])
    t0 = clock.now_ns()
    flicker = ["G1", "G2", "G1", "G2", "G2", "G3"]
    writer.append("gestures_live", spec.format_rows([(k, t0 + k * 100_000_000, c, 0.5, "G1" if k < 4 else "G2")
                                                     for k, c in enumerate(flicker)]))
    writer.finalize("complete", "test", t0 + 1_000_000_000, {})
    return writer.folder


def test_a_marker_stream_sends_its_marker_column_as_pyxdf_reads_it(tmp_path: Path) -> None:
    """gestures_live's one string channel is the decoded gesture (its manifest's marker), not the first
    text column (the raw class, which flickers); a manifest naming a non-text marker is refused."""
    import pyxdf

    session = _session_with_gestures(tmp_path / "in", "decoded")
    assert midas("export", str(session), "--format", "xdf", "--out", str(tmp_path / "out")).returncode == 0
    (path,) = (tmp_path / "out").glob("*.xdf")
    streams, _ = pyxdf.load_xdf(str(path))
    (stream,) = [s for s in streams if s["info"]["name"] == ["gestures_live"]]
    assert stream["info"]["type"] == ["Markers"] and stream["info"]["channel_format"] == ["string"]
    assert [c["label"][0] for c in stream["info"]["desc"][0]["channels"][0]["channel"]] == ["decoded"]
    assert [row[0] for row in stream["time_series"]] == ["G1"] * 4 + ["G2"] * 2

    manifest_path = session / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    assert manifest["streams"]["gestures_live"]["marker"] == "decoded"
    for bad in ("probability", "nothing", ["decoded"]):
        manifest["streams"]["gestures_live"]["marker"] = bad
        manifest_path.write_text(json.dumps(manifest))
        result = midas("export", str(session), "--format", "xdf", "--out", str(tmp_path / f"bad-{len(str(bad))}"))
        errors = [line for line in result.stderr.splitlines() if line.startswith("midas: error:")]
        assert result.returncode != 0 and len(errors) == 1 and "marker" in errors[0], result.stderr
        assert not any(p.is_file() for p in (tmp_path / f"bad-{len(str(bad))}").rglob("*"))  # no file, no torn one
