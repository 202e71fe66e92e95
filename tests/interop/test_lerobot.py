"""`midas export --format lerobot`: a LeRobot v3.0 dataset of one episode on the aligned frame clock.

The layout and values are checked here with pyarrow/pandas/OpenCV; ``test_lerobot_loads_*`` load the
export with huggingface lerobot's own ``LeRobotDataset`` in its own environment (``make lerobot-env``:
lerobot's pins clash with midas's). Without that environment they skip, unless MIDAS_REQUIRE_LEROBOT=1.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from midas_cli.session.derived import read_aligned
from midas_cli.session.labels import write_frame_labels
from midas_cli.session.reader import Session
from midas_cli.session.sync_statement import statement
from helpers.analysis_sessions import raven_session
from helpers.cli import REPO, midas

DURATION_S = 3.0  # 90 video frames at 30 Hz
DROPPED = (30, 31, 32)  # recording frames the video stream has no stamp for
MARKERS = ((0.51, "needle in"), (0.52, "grip"), (2.0, "knot"))
LEROBOT_VENV = REPO / ".venv-lerobot"  # `make lerobot-env`; its .installed stamp is written last
LEROBOT_PYTHON = Path(os.environ.get("MIDAS_LEROBOT_PYTHON", LEROBOT_VENV / "bin" / "python"))
STATE_SOURCES = ("emht", "mtm", "psm")


def _colour(frame: int) -> tuple[int, int, int]:
    """The flat BGR colour of recording frame ``frame``: 125 colours at least 45 apart per channel, so
    a frame is told from every other after two lossy codings (which move a channel by up to ~10)."""
    return tuple(40 + 45 * (frame // 5 ** k % 5) for k in range(3))


def _write_recording(session: Path, frames: int) -> None:
    import cv2

    writer = cv2.VideoWriter(str(session / "video" / "endoscope.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30, (64, 48))
    for k in range(frames):
        writer.write(np.full((48, 64, 3), _colour(k), np.uint8))
    writer.release()


def _labels(frames: np.ndarray) -> list[str]:
    return ["" if f < 10 else ("G1" if f < 50 else "G3") for f in frames.tolist()]


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """One session exported before `midas align` (refused), without a recording and with one."""
    root = tmp_path_factory.mktemp("lerobot")
    session = raven_session(root / "in", duration_s=DURATION_S, markers=MARKERS, dropped_frames=DROPPED)
    refused = midas("export", str(session), "--format", "lerobot", "--out", str(root / "refused"))
    midas("align", str(session), check=True)
    frames = np.arange(int(DURATION_S * 30))
    write_frame_labels(session, frames, _labels(frames), {"taxonomy": "JIGSAWS", "source": "test"})
    bare = midas("export", str(session), "--format", "lerobot", "--out", str(root / "bare"), "--json")
    _write_recording(session, len(frames))
    filmed = midas("export", str(session), "--format", "lerobot", "--out", str(root / "filmed"), "--json")
    return {"session": session, "refused": refused, "bare": bare, "filmed": filmed}


def _dataset(exported: dict[str, Any], which: str) -> Path:
    result = exported[which]
    assert result.returncode == 0, result.stderr
    return Path(json.loads(result.stdout)[0]["lerobot"]["folder"])


def test_export_without_an_aligned_table_is_refused(exported: dict[str, Any]) -> None:
    refused = exported["refused"]
    assert refused.returncode == 4 and "midas align" in refused.stderr and "Traceback" not in refused.stderr
    assert not any((exported["session"].parent.parent / "refused").glob("*.lerobot"))


def test_layout_is_lerobot_v3(exported: dict[str, Any]) -> None:
    """info.json, tasks, the episode row and the data file agree with each other and with LeRobot v3.0's
    layout (lerobot 0.4.4 datasets/utils.py: paths, DEFAULT_FEATURES, get_hf_features_from_features)."""
    root = _dataset(exported, "filmed")
    info = json.loads((root / "meta/info.json").read_text())
    table = read_aligned(exported["session"])
    assert info["codebase_version"] == "v3.0" and info["fps"] == 30
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"]) == (1, len(table.frame), 1)
    features = info["features"]
    for name in ("timestamp", "frame_index", "episode_index", "index", "task_index"):
        assert features[name]["shape"] == [1] and features[name]["dtype"] in ("float32", "int64")
    data = pq.read_table(root / info["data_path"].format(chunk_index=0, file_index=0))
    assert data.column_names == [k for k, f in features.items() if f["dtype"] != "video"]
    for name, feature in features.items():
        if feature["dtype"] != "video" and feature["shape"] != [1]:
            assert data.schema.field(name).type.list_size == feature["shape"][0] == len(feature["names"])
    video = features["observation.images.endoscope"]
    assert video["dtype"] == "video" and video["shape"] == [48, 64, 3] and video["info"]["video.fps"] == 30
    assert (root / info["video_path"].format(video_key="observation.images.endoscope", chunk_index=0,
                                             file_index=0)).is_file()
    tasks = pd.read_parquet(root / "meta/tasks.parquet")
    assert tasks.index.tolist() == ["peg-transfer"] and tasks["task_index"].tolist() == [0]
    episode = pd.read_parquet(root / "meta/episodes/chunk-000/file-000.parquet").iloc[0]
    assert (episode["episode_index"], episode["length"], episode["dataset_to_index"]) == (0, len(table.frame),
                                                                                         len(table.frame))
    assert episode["videos/observation.images.endoscope/to_timestamp"] == pytest.approx(len(table.frame) / 30)
    assert (episode["subject"], episode["trial"], list(episode["tasks"])) == ("1", 1, ["peg-transfer"])
    assert json.loads((root / "meta/stats.json").read_text())["observation.state"]["count"] == [len(table.frame)]


def test_frames_carry_the_session_values(exported: dict[str, Any]) -> None:
    """Row k is aligned frame k: its state, times, labels and markers are the session's."""
    root = _dataset(exported, "filmed")
    info = json.loads((root / "meta/info.json").read_text())
    data = pd.read_parquet(root / "data/chunk-000/file-000.parquet")
    table = read_aligned(exported["session"])
    assert 30 not in table.frame.tolist() and data["video_frame"].tolist() == table.frame.tolist()
    assert data["t_host_ns"].tolist() == table.t_host_ns.tolist()
    assert np.allclose(data["timestamp"], np.arange(len(data)) / 30)  # the MP4's constant-rate clock
    names = info["features"]["observation.state"]["names"]
    sources = {c["name"]: c["source"] for c in table.meta["columns"]}  # clutch: from the mtm stream here
    assert names == [c for c in table.columns if sources[c] in STATE_SOURCES and not c.endswith("_delta_ms")]
    assert len(names) > 40 and {"emht.s1_x_mm", "mtm.left_x_mm", "psm.right_qw", "clutch"} <= set(names)
    state = np.stack(data["observation.state"].to_numpy())
    expected = np.column_stack([table.column(c) for c in names]).astype(np.float32)
    assert np.array_equal(state, expected, equal_nan=True)
    assert data["label.gestures"].tolist() == _labels(table.frame)
    start = int(Session.open(exported["session"]).read_stream("video")["t_host_ns"].iloc[0])
    marked = {k: m for k, m in enumerate(data["marker"]) if m}
    row_of = {t: int(np.searchsorted(table.t_host_ns, start + round(t * 1e9), side="right")) - 1 for t, _ in MARKERS}
    assert marked == {row_of[0.51]: "needle in | grip", row_of[2.0]: "knot"} and row_of[0.51] == 15
    midas_meta = json.loads((root / "meta/midas.json").read_text())
    sync, document = info["midas"]["sync"], info["midas"]["sync_statement"]
    assert document == statement(exported["session"], Session.open(exported["session"]).manifest)
    assert document["method"] in sync and "video frame clock" in sync and "endoscope.mp4" in sync
    assert sync == midas_meta["sync"] and midas_meta["aligned"]["method"] in sync
    assert (info["midas"]["subject"], info["midas"]["task"], info["midas"]["trial"]) == ("1", "peg-transfer", 1)


def test_video_frames_follow_the_frame_clock(exported: dict[str, Any]) -> None:
    """MP4 frame k is recording frame video_frame[k]: the frames the stream lacks are not in the episode."""
    import cv2

    root = _dataset(exported, "filmed")
    frames = pd.read_parquet(root / "data/chunk-000/file-000.parquet")["video_frame"].to_numpy()
    capture = cv2.VideoCapture(str(root / "videos/observation.images.endoscope/chunk-000/file-000.mp4"))
    decoded = []
    while True:
        ok, image = capture.read()
        if not ok:
            break
        decoded.append(image.reshape(-1, 3).mean(axis=0))
    capture.release()
    assert len(decoded) == len(frames)
    expected = np.array([_colour(f) for f in frames.tolist()], dtype=float)
    assert np.abs(np.array(decoded) - expected).max() < 15


def test_session_without_a_recording_has_no_video_feature(exported: dict[str, Any]) -> None:
    result = exported["bare"]
    root = _dataset(exported, "bare")
    info = json.loads((root / "meta/info.json").read_text())
    assert info["video_path"] is None and not any(f["dtype"] == "video" for f in info["features"].values())
    assert not (root / "videos").exists() and "no video recording" in info["midas"]["sync"]
    assert "no video recording" in result.stderr and json.loads(result.stdout)[0]["lerobot"]["video"] is False


def _load_with_lerobot(root: Path, video: bool = False) -> dict[str, Any]:
    """What huggingface lerobot's LeRobotDataset reads from ``root`` (tests/helpers/lerobot_load.py)."""
    chosen = "MIDAS_LEROBOT_PYTHON" in os.environ
    ready = LEROBOT_PYTHON.is_file() if chosen else (LEROBOT_VENV / ".installed").is_file()
    if not ready:
        message = f"no LeRobot environment at {LEROBOT_PYTHON}: run `make lerobot-env`"
        if os.environ.get("MIDAS_REQUIRE_LEROBOT") == "1":
            pytest.fail(message)
        pytest.skip(message)
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HOME": str(root.parent / "hf-home")}
    env.pop("PYTHONPATH", None)
    done = subprocess.run([str(LEROBOT_PYTHON), str(REPO / "tests/helpers/lerobot_load.py"), str(root),
                           *(["--video"] if video else [])], check=False, capture_output=True, text=True,
                          timeout=300, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout)


def test_lerobot_loads_the_episode(exported: dict[str, Any]) -> None:
    """LeRobot's own loader gives every frame with the session's values, its task and labels."""
    root = _dataset(exported, "bare")
    loaded = _load_with_lerobot(root)
    table = read_aligned(exported["session"])
    assert (loaded["len"], loaded["fps"], loaded["episodes"]) == (len(table.frame), 30, 1)
    assert loaded["tasks"] == ["peg-transfer", "peg-transfer"]
    frames = loaded["frames"]
    assert frames["frame_index"] == list(range(len(table.frame))) and frames["video_frame"] == table.frame.tolist()
    assert frames["t_host_ns"] == table.t_host_ns.tolist()
    names = loaded["features"]["observation.state"]["names"]
    state = np.array(frames["observation.state"], dtype=np.float64)  # None (NaN) -> nan
    expected = np.column_stack([table.column(c) for c in names]).astype(np.float32)
    assert np.array_equal(state.astype(np.float32), expected, equal_nan=True)
    assert np.array_equal(np.array(loaded["item_state"], dtype=np.float64).astype(np.float32), expected[5],
                          equal_nan=True)
    assert frames["label.gestures"] == _labels(table.frame)
    assert [k for k, m in enumerate(frames["marker"]) if m] == [15, 60 - len(DROPPED)]


def test_lerobot_decodes_the_video(exported: dict[str, Any]) -> None:
    """LeRobot's own loader decodes the frame of each row at its timestamp."""
    root = _dataset(exported, "filmed")
    loaded = _load_with_lerobot(root, video=True)
    if "video_error" in loaded:
        message = f"lerobot could not decode the video here: {loaded['video_error']}"
        if os.environ.get("MIDAS_REQUIRE_LEROBOT") == "1":
            pytest.fail(message)
        pytest.skip(message)
    frames = read_aligned(exported["session"]).frame
    for row, means in loaded["video"].items():
        blue, green, red = _colour(int(frames[int(row)]))
        assert np.allclose(means, [red, green, blue], atol=15), (row, means)


def test_fps_and_stats_of_awkward_tables() -> None:
    """fps is the nearest whole rate (LeRobot's is an int); stats skip masked (NaN) values."""
    from midas_cli.errors import SessionError
    from midas_cli.interop.lerobot_export import nominal_fps, vector_stats

    assert nominal_fps(np.round(np.arange(100) * 1e9 / 29.97).astype(np.int64)) == 30
    with pytest.raises(SessionError):
        nominal_fps(np.array([5], dtype=np.int64))
    stats = vector_stats(np.array([[1.0, np.nan], [3.0, np.nan], [np.nan, np.nan]]))
    assert stats["mean"][0] == 2.0 and stats["min"][0] == 1.0 and stats["max"][0] == 3.0 and stats["std"][0] == 1.0
    assert np.isnan(stats["mean"][1]) and np.isnan(stats["min"][1]) and stats["count"].tolist() == [3]
