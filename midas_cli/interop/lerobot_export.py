"""A session as a LeRobot dataset of one episode: ``<out>/<session_id>.lerobot/``

The layout is LeRobot's dataset format v3.0 (``codebase_version`` "v3.0", read by ``lerobot`` 0.4.x
``LeRobotDataset(repo_id, root=...)``); the older v2.1 layout is not written:

* ``data/chunk-000/file-000.parquet``: one row per frame of the aligned table (``midas align``), in frame
  order: ``timestamp`` (float32 s = row / fps, the episode's video time), ``frame_index``,
  ``episode_index`` (0), ``index``, ``task_index`` (0), ``observation.state`` (float32: the EmHT and robot
  kinematics columns, NaN where masked), ``observation.<stream>`` (float32: every other aligned column,
  grouped by source stream), ``observation.delta_ms`` (each stream's chosen sample time - frame time, ms;
  a vector of one is stored as a scalar, as LeRobot reads shape (1,)), ``video_frame`` (the video
  ``seq``), ``t_host_ns`` (the frame's host time),
  ``label.<set>`` (each label set's label of the frame, "" = unlabelled) and ``marker`` (the operator's
  markers stamped while the frame was current, joined with " | ", "" = none);
* ``videos/observation.images.endoscope/chunk-000/file-000.mp4`` when the session's ``video/`` folder
  holds a recording: MP4 frame k = recording frame ``video_frame`` of row k, constant rate ``fps``
  (MPEG-4 part 2 through OpenCV). A session without a recording (simulated ones) gets no video feature;
  the sync statement says so;
* ``meta/info.json`` (features, fps, paths; ``midas`` holds the session, subject/task/trial, the sync
  statement in words and the session's full one, session/sync_statement.py), ``meta/stats.json`` and
  the episode's ``stats/*`` (min, max, mean, std, count; NaN-aware),
  ``meta/tasks.parquet`` (the session's task), ``meta/episodes/chunk-000/file-000.parquet`` (the episode:
  length, indices, video timestamps, session_id/subject/trial) and ``meta/midas.json`` (the sync
  statement, the manifest and the aligned table's metadata).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.errors import SessionError
from midas_cli.interop.lerobot_video import write_video
from midas_cli.session.derived import AlignedTable, read_aligned
from midas_cli.session.labels import list_label_sets, read_frame_labels
from midas_cli.session.outputs import out_child_folder
from midas_cli.session.pedals_gt import session_videos
from midas_cli.session.reader import Session
from midas_cli.session.sync_statement import statement

log = logging.getLogger(__name__)

CODEBASE_VERSION = "v3.0"
STATE_SOURCES = ("emht", "mtm", "psm")  # streams whose aligned columns make observation.state
VIDEO_KEY = "observation.images.endoscope"
EVENTS_STREAM = "events"
DATA_FILE = "data/chunk-000/file-000.parquet"
EPISODES_FILE = "meta/episodes/chunk-000/file-000.parquet"
VIDEO_FILE = f"videos/{VIDEO_KEY}/chunk-000/file-000.mp4"
MARKER_JOIN = " | "
INDEX_FEATURES = ("timestamp", "frame_index", "episode_index", "index", "task_index")  # LeRobot's DEFAULT_FEATURES
FLOAT32_EXACT_S = 2048  # from here a float32 timestamp's step (2**-12 s) exceeds LeRobot's 1e-4 s tolerance


@dataclass
class Episode:
    """One session's frames, ready to write: vector features (N, k) float32, per-frame ints and strings."""

    fps: int
    frames: np.ndarray
    t_host_ns: np.ndarray
    vectors: dict[str, tuple[list[str], np.ndarray]]
    strings: dict[str, list[str]]
    task: str
    session: dict[str, Any]
    aligned_meta: dict[str, Any] = field(default_factory=dict)
    video: Path | None = None
    notes: list[str] = field(default_factory=list)


def nominal_fps(t_host_ns: np.ndarray) -> int:
    """The frame rate (whole frames per second, as LeRobot's ``fps`` is an int) from the median frame
    interval on the host clock; SessionError when there are fewer than two frames."""
    if len(t_host_ns) < 2:
        raise SessionError(f"the aligned table has {len(t_host_ns)} frame(s): a LeRobot episode needs two or more")
    interval = float(np.median(np.diff(t_host_ns)))
    if interval <= 0:
        raise SessionError("the aligned table's frame times do not increase: re-run `midas align`")
    return max(1, round(1e9 / interval))


def _column_sources(table: AlignedTable) -> list[str]:
    """Each aligned column's source stream (aligned.json's ``source``, else the name before '.' or
    '_delta_ms')."""
    described = {c.get("name"): c.get("source") for c in table.meta.get("columns", []) if isinstance(c, dict)}
    sources = []
    for name in table.columns:
        source = described.get(name)
        sources.append(str(source) if source else name.split(".", 1)[0].removesuffix("_delta_ms"))
    return sources


def _feature_of(name: str, source: str) -> str:
    """The vector feature an aligned column goes to."""
    if name.endswith("_delta_ms"):
        return "observation.delta_ms"
    return "observation.state" if source in STATE_SOURCES else f"observation.{source}"


def vector_features(table: AlignedTable) -> dict[str, tuple[list[str], np.ndarray]]:
    """``observation.state`` (the EmHT and robot kinematics columns), ``observation.<source>`` per other
    source stream and ``observation.delta_ms`` (each stream's chosen sample time - frame time): (column
    names, (N, k) float32 values, NaN where masked)."""
    groups: dict[str, list[int]] = {}
    for k, (name, source) in enumerate(zip(table.columns, _column_sources(table))):
        groups.setdefault(_feature_of(name, source), []).append(k)
    return {key: ([table.columns[k] for k in ks], np.asarray(table.values[:, ks], dtype=np.float32))
            for key, ks in groups.items()}


def frame_labels(session: Session, frames: np.ndarray) -> dict[str, list[str]]:
    """``label.<set>``: each label set's label of every aligned frame ("" where the set has none)."""
    result = {}
    for name in list_label_sets(session.path):
        labels = read_frame_labels(session.path, name)
        by_frame = dict(zip(labels.frames.tolist(), (str(v) for v in labels.labels)))
        result[f"label.{name}"] = [by_frame.get(f, "") for f in frames.tolist()]
    return result


def frame_markers(session: Session, t_host_ns: np.ndarray) -> tuple[list[str], int]:
    """The markers of the ``events`` stream per frame: a marker belongs to the last frame stamped at or
    before it (host clock). Returns the per-frame texts and how many markers fell before the first frame
    or after the last frame's interval (left out)."""
    texts: list[list[str]] = [[] for _ in range(len(t_host_ns))]
    if EVENTS_STREAM not in session.stream_names:
        return ["" for _ in texts], 0
    left_out = 0
    period = int(np.median(np.diff(t_host_ns))) if len(t_host_ns) > 1 else 0
    for chunk in session.iter_stream(EVENTS_STREAM):
        for stamp, text in zip(chunk["t_host_ns"].tolist(), chunk["text"].tolist()):
            row = int(np.searchsorted(t_host_ns, stamp, side="right")) - 1
            if row < 0 or stamp >= t_host_ns[-1] + period:
                left_out += 1
                continue
            texts[row].append("" if not isinstance(text, str) else text)  # a missing text (None, NaN, NA): ""
    return [MARKER_JOIN.join(t) for t in texts], left_out


def session_facts(session: Session) -> dict[str, Any]:
    """session_id, subject, task, trial and platform from the manifest (None where it lacks them)."""
    metadata = session.manifest.get("metadata") or {}
    subject, trial = metadata.get("subject"), metadata.get("trial")
    return {"session_id": str(session.manifest.get("session_id") or session.path.name),
            "subject": None if subject is None else str(subject),
            "task": None if metadata.get("task") is None else str(metadata["task"]),
            "trial": trial if isinstance(trial, int) and not isinstance(trial, bool) else None,
            "platform": None if metadata.get("platform") is None else str(metadata["platform"])}


def build_episode(session: Session) -> Episode:
    """Everything the dataset holds, from the aligned table, the label sets, the markers and the video."""
    table = read_aligned(session.path)
    frames = np.asarray(table.frame, dtype=np.int64)
    t_host_ns = np.asarray(table.t_host_ns, dtype=np.int64)
    fps = nominal_fps(t_host_ns)
    markers, left_out = frame_markers(session, t_host_ns)
    facts = session_facts(session)
    episode = Episode(fps, frames, t_host_ns, vector_features(table),
                      {**frame_labels(session, frames), "marker": markers}, facts["task"] or "unspecified", facts,
                      {k: v for k, v in table.meta.items() if k != "columns"})
    if left_out:
        episode.notes.append(f"{left_out} marker(s) stamped outside the aligned frames were left out")
    if len(frames) / fps >= FLOAT32_EXACT_S:
        episode.notes.append(f"the episode lasts {len(frames) / fps:.0f} s: past {FLOAT32_EXACT_S} s LeRobot's float32 "
                             f"timestamps are coarser than its default 1e-4 s video tolerance; load it with "
                             f"LeRobotDataset(..., tolerance_s=5e-4)")
    videos = session_videos(session.path)
    if videos:
        episode.video = videos[0]
        if len(videos) > 1:
            episode.notes.append(f"{len(videos)} recordings in video/: {videos[0].name} exported")
    else:
        episode.notes.append("the session has no video recording (video/ is empty): no video feature")
    return episode


def sync_statement(session: Session, episode: Episode, method: str) -> str:
    """How the streams were synchronised and put on the episode's clock, in words (for collections that
    ask for one); ``method`` is the session's sync statement's (session/sync_statement.py)."""
    streams = ", ".join(session.stream_names)
    measured = (len(episode.t_host_ns) - 1) * 1e9 / max(1, int(episode.t_host_ns[-1] - episode.t_host_ns[0]))
    video = (f"MP4 frame k is recording frame video_frame[k] ({episode.video.name}), written at a constant "
             f"{episode.fps} fps" if episode.video is not None else "no video recording exists for this session")
    return (f"Streams {streams}: {method}. `midas align` then put every stream on the "
            f"video frame clock: one row per video frame (video_frame = the video stream's seq, t_host_ns = "
            f"the frame's host time), each stream's sample chosen by the method "
            f"'{episode.aligned_meta.get('method', 'unknown')}' (a value too old or missing is NaN). "
            f"timestamp = row / fps with fps = {episode.fps} (the median frame interval; measured "
            f"{measured:.3f} frames/s over the episode); the true frame times are "
            f"t_host_ns. Video: {video}.")


def vector_stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """min, max, mean, std per column of (N, k) values, NaN (masked samples) ignored; NaN for a column
    without a valid value; count = N."""
    valid = np.isfinite(values)
    safe = np.where(valid, values, 0.0).astype(np.float64)
    n = valid.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = safe.sum(axis=0) / n
        std = np.sqrt(np.where(valid, (safe - mean) ** 2, 0.0).sum(axis=0) / n)
    low = np.where(valid, values, np.inf).min(axis=0, initial=np.inf)
    high = np.where(valid, values, -np.inf).max(axis=0, initial=-np.inf)
    return {"min": np.where(n > 0, low, np.nan), "max": np.where(n > 0, high, np.nan), "mean": mean, "std": std,
            "count": np.array([len(values)])}


def features_of(episode: Episode) -> dict[str, dict[str, Any]]:
    """info.json ``features`` for everything but the video (added when a recording is written)."""
    features: dict[str, dict[str, Any]] = {
        name: {"dtype": "float32" if name == "timestamp" else "int64", "shape": [1], "names": None}
        for name in INDEX_FEATURES}
    for key, (names, _) in episode.vectors.items():
        features[key] = {"dtype": "float32", "shape": [len(names)], "names": names}
    features["video_frame"] = {"dtype": "int64", "shape": [1], "names": None}
    features["t_host_ns"] = {"dtype": "int64", "shape": [1], "names": None}
    for key in episode.strings:
        features[key] = {"dtype": "string", "shape": [1], "names": None}
    return features


def data_table(episode: Episode) -> Any:
    """The episode's rows as an Arrow table, columns in ``features_of`` order."""
    import pyarrow as pa

    n = len(episode.frames)
    rows = np.arange(n, dtype=np.int64)
    columns: dict[str, Any] = {
        "timestamp": pa.array((rows / episode.fps).astype(np.float32)),
        "frame_index": pa.array(rows), "episode_index": pa.array(np.zeros(n, np.int64)),
        "index": pa.array(rows), "task_index": pa.array(np.zeros(n, np.int64))}
    for key, (names, values) in episode.vectors.items():
        flat = pa.array(np.ascontiguousarray(values, dtype=np.float32).reshape(-1))
        single = len(names) == 1  # LeRobot reads shape (1,) as a scalar column
        columns[key] = flat if single else pa.FixedSizeListArray.from_arrays(flat, len(names))
    columns["video_frame"] = pa.array(episode.frames)
    columns["t_host_ns"] = pa.array(episode.t_host_ns)
    for key, texts in episode.strings.items():
        columns[key] = pa.array(texts, pa.string())
    return pa.table(columns)


def episode_stats(episode: Episode, video_stats: dict[str, np.ndarray] | None) -> dict[str, dict[str, np.ndarray]]:
    """Stats per numeric feature (LeRobot's stats.json; one episode, so the episode's are the dataset's)."""
    n = len(episode.frames)
    rows = np.arange(n, dtype=np.float64)[:, None]
    stats = {"timestamp": vector_stats(rows / episode.fps), "frame_index": vector_stats(rows),
             "episode_index": vector_stats(np.zeros((n, 1))), "index": vector_stats(rows),
             "task_index": vector_stats(np.zeros((n, 1))),
             "video_frame": vector_stats(episode.frames[:, None].astype(np.float64)),
             "t_host_ns": vector_stats(episode.t_host_ns[:, None].astype(np.float64))}
    stats.update({key: vector_stats(values.astype(np.float64)) for key, (_, values) in episode.vectors.items()})
    if video_stats is not None:
        stats[VIDEO_KEY] = video_stats
    return stats


def _jsonable(stats: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, Any]]:
    return {key: {name: _finite(np.asarray(value).tolist()) for name, value in parts.items()}
            for key, parts in stats.items()}


def _finite(value: Any) -> Any:
    """NaN -> None, recursively (JSON has no NaN)."""
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return None if isinstance(value, float) and math.isnan(value) else value


def episodes_table(episode: Episode, stats: dict[str, dict[str, np.ndarray]], video: bool) -> Any:
    """``meta/episodes/chunk-000/file-000.parquet``: the one episode's row."""
    import pyarrow as pa

    n = len(episode.frames)
    row: dict[str, Any] = {"episode_index": 0, "tasks": [episode.task], "length": n,
                           "data/chunk_index": 0, "data/file_index": 0,
                           "dataset_from_index": 0, "dataset_to_index": n}
    if video:
        row.update({f"videos/{VIDEO_KEY}/chunk_index": 0, f"videos/{VIDEO_KEY}/file_index": 0,
                    f"videos/{VIDEO_KEY}/from_timestamp": 0.0, f"videos/{VIDEO_KEY}/to_timestamp": n / episode.fps})
    row.update({"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0})
    row.update({k: episode.session[k] for k in ("session_id", "subject", "trial")})
    for key, parts in stats.items():
        for name, value in parts.items():
            row[f"stats/{key}/{name}"] = _finite(np.asarray(value).tolist())
    types = {"session_id": pa.string(), "subject": pa.string(), "trial": pa.int64()}
    return pa.table({k: pa.array([v], types.get(k)) for k, v in row.items()})


def info_document(episode: Episode, features: dict[str, Any], sync: str, document: dict[str, Any],
                  video: bool) -> dict[str, Any]:
    """``meta/info.json``: LeRobot's fields, then ``midas`` (session facts, the sync statement in words
    and the session's full sync statement)."""
    n = len(episode.frames)
    return {"codebase_version": CODEBASE_VERSION, "robot_type": episode.session.get("platform"),
            "total_episodes": 1, "total_frames": n, "total_tasks": 1, "chunks_size": 1000,
            "data_files_size_in_mb": 100, "video_files_size_in_mb": 200, "fps": episode.fps,
            "splits": {"train": "0:1"}, "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
            "video_path": ("videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4" if video else None),
            "features": features,
            "midas": {**episode.session, "sync": sync, "sync_statement": document, "notes": episode.notes,
                      "details": "meta/midas.json"}}


def write_lerobot(session: Session, out_dir: Path, name: str) -> dict[str, Any]:
    """Write the dataset as folder ``name`` of ``out_dir`` (an earlier export there is replaced whole;
    nothing is created when the session cannot be exported); returns the folder, frames, fps, whether a
    video was written and the notes."""
    import pandas as pd
    import pyarrow.parquet as pq

    episode = build_episode(session)
    folder = out_child_folder(out_dir, name)
    build = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp", dir=folder.parent))
    try:
        features, video_stats = features_of(episode), None
        if episode.video is not None:
            (build / VIDEO_FILE).parent.mkdir(parents=True)
            written = write_video(episode.video, episode.frames, episode.fps, build / VIDEO_FILE)
            features[VIDEO_KEY], video_stats = written["feature"], written["stats"]
        stats = episode_stats(episode, video_stats)
        document = statement(session.path, session.manifest)
        sync = sync_statement(session, episode, document["method"])
        for relative in (DATA_FILE, EPISODES_FILE):
            (build / relative).parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(data_table(episode), build / DATA_FILE)
        pq.write_table(episodes_table(episode, stats, episode.video is not None), build / EPISODES_FILE)
        pd.DataFrame({"task_index": [0]}, index=pd.Index([episode.task], name="task")).to_parquet(
            build / "meta/tasks.parquet")
        _write_json(build / "meta/info.json", info_document(episode, features, sync, document,
                                                            episode.video is not None))
        _write_json(build / "meta/stats.json", _jsonable(stats))
        _write_json(build / "meta/midas.json", {"sync": sync, "sync_statement": document, "notes": episode.notes,
                                                "session": episode.session, "manifest": session.manifest,
                                                "aligned": episode.aligned_meta})
        _swap_in(build, folder)
    except BaseException:
        shutil.rmtree(build, ignore_errors=True)
        raise
    for note in episode.notes:
        log.warning("%s: %s", session.path, note)
    return {"folder": str(folder), "frames": len(episode.frames), "fps": episode.fps,
            "video": episode.video is not None, "format": f"LeRobot {CODEBASE_VERSION}", "notes": episode.notes}


def _write_json(path: Path, document: Any) -> None:
    path.write_text(json.dumps(document, indent=2, default=str) + "\n", encoding="utf-8")


def _swap_in(build: Path, folder: Path) -> None:
    """Rename the finished ``build`` folder to ``folder``; an earlier export there is removed after."""
    old = None
    if folder.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".old", dir=folder.parent))
        os.replace(folder, old / folder.name)
    os.replace(build, folder)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
