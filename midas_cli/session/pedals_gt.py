"""Pedal ground truth read from the console video: where it lives and how it is written.

* A session's recordings are the video files in ``video/`` (MKV, MP4, AVI, MOV).
* Frame times come from the session's video stream (``seq`` = 0-based frame index, ``t_host_ns`` =
  host clock), the stream named "video" or else the stream of a device of kind "video".
* Results: ``derived/pedals_gt.csv`` (``frame,t_host_ns,<pedal>...``, 0/1 per pedal, empty time where
  the stream has no row for a frame) with ``derived/pedals_gt.json`` beside it stating the frame
  convention, the source video and the layout. A bare video gets the same pair of files elsewhere.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Any

import pandas as pd

from midas_cli.errors import SessionError
from midas_cli.session.derived import PEDALS_GT
from midas_cli.session.labels import FRAME_CONVENTION
from midas_cli.session.manifest import MANIFEST_NAME
from midas_cli.session.outputs import replacing, session_lock, session_of, session_target
from midas_cli.session.reader import Session

VIDEO_DIR = "video"
VIDEO_SUFFIXES = (".mkv", ".mp4", ".avi", ".mov")

__all__ = ["FRAME_CONVENTION", "PEDALS_GT", "session_of_video", "session_videos", "video_frame_times",
           "pedals_gt_path", "write_pedals_gt"]


def session_videos(session_path: Path | str) -> list[Path]:
    """Video files in the session's ``video/`` folder, sorted by name."""
    folder = Path(session_path) / VIDEO_DIR
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)


def the_session_video(session_path: Path) -> Path:
    """The one video of a session folder given where a video is expected; SessionError, naming what is
    there, when the folder is no session or holds no or several videos."""
    if not (session_path / MANIFEST_NAME).is_file():
        raise SessionError(f"{session_path} is a folder without {MANIFEST_NAME}: give a session folder or a video file")
    videos = session_videos(session_path)
    if len(videos) != 1:
        found = ", ".join(v.name for v in videos) or "none"
        raise SessionError(f"session {session_path} has {len(videos)} videos in video/ ({found}); "
                           f"give the video file itself, e.g. {session_path}/video/<file>")
    return videos[0]


def session_of_video(video_path: Path | str) -> Path | None:
    """The session folder a video file sits in (``<session>/video/<file>``), or None for a bare file."""
    parent = Path(video_path).resolve().parent
    if parent.name == VIDEO_DIR and (parent.parent / MANIFEST_NAME).is_file():
        return parent.parent
    return None


def video_frame_times(session: Session) -> tuple[str | None, pd.Series]:
    """(stream name, t_host_ns indexed by frame seq) of the session's video stream; (None, empty) if none."""
    names = [n for n in session.stream_names if n == "video"] or [
        n for n in session.stream_names
        if session.manifest["devices"].get(session.manifest["streams"][n].get("device"), {}).get("kind") == "video"]
    if not names:
        return None, pd.Series(dtype="int64")
    frame = session.read_stream(names[0], allow_incomplete=True)
    times = frame.drop_duplicates("seq").set_index("seq")["t_host_ns"]
    return names[0], times


def pedals_gt_path(session_path: Path | str) -> Path:
    """``derived/pedals_gt.csv`` of a session (its folder created; refused if it leads out)."""
    return session_target(session_path, PEDALS_GT)


def write_pedals_gt(csv_path: Path | str, table: pd.DataFrame, meta: dict[str, Any]) -> tuple[Path, Path]:
    """Write ``table`` as CSV and ``meta`` (plus the frame convention) as the JSON sidecar, atomically."""
    csv_path = Path(csv_path)
    if "frame" not in table.columns:
        raise SessionError("a pedal ground-truth table needs a 'frame' column")
    json_path = csv_path.with_suffix(".json")
    session = session_of(csv_path.parent)
    with session_lock(session) if session else contextlib.nullcontext(), replacing(json_path) as tmp_json, \
            replacing(csv_path) as tmp_csv:
        table.to_csv(tmp_csv, index=False)
        full = {"frame_convention": FRAME_CONVENTION, **meta}
        tmp_json.write_text(json.dumps(full, indent=2, default=str) + "\n", encoding="utf-8")
    return csv_path, json_path
