"""`midas extract pedals` as a library: session or bare video in, pedal-state table + sidecar out.

Frame convention: row ``frame`` = 0-based index of the decoded video frame = ``seq`` of the session's
video stream. (The original MiDAS scripts numbered the energy-pedal frames from 1 and the camera and
arm-swap frames from 0, and shifted their merge by one frame; here every table uses the same index.)
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

import pandas as pd

from midas_cli import __version__
from midas_cli.analysis.pedal_video.extract import PedalStates, debounce, extract_pedal_states
from midas_cli.analysis.pedal_video.layout import load_layout
from midas_cli.errors import ConfigError, SessionError
from midas_cli.session.outputs import out_target
from midas_cli.session.pedals_gt import (pedals_gt_path, session_of_video, the_session_video, video_frame_times,
                                         write_pedals_gt)
from midas_cli.session.reader import Session

log = logging.getLogger(__name__)

ORIGINAL_NOTE = ("the original MiDAS scripts wrote energy pedals with 1-based 'Frame Num' and camera/arm-swap "
                 "pedals with 0-based 'obs_frame_idx'; midas uses 0-based frames everywhere")


@dataclass(frozen=True)
class GroundTruthRequest:
    """One input: a session folder or a video file; ``out`` overrides the CSV path (bare videos)."""

    input: Path
    layout: str = "davinci-xi"
    view: str = "auto"
    min_duration: int = 1
    out: Path | None = None


@dataclass
class GroundTruthResult:
    input: str
    video: str
    session: str | None
    csv: str
    sidecar: str
    frames: int
    fps: float
    wall_s: float
    pressed_fraction: dict[str, float] = field(default_factory=dict)
    frames_without_host_time: int = 0

    @property
    def speed_fps(self) -> float:
        """Frames processed per second of wall time."""
        return self.frames / self.wall_s if self.wall_s > 0 else float("inf")


def resolve_input(path: Path, out: Path | None) -> tuple[Path, Path | None, Path]:
    """(video file, session folder or None, output CSV) for a session folder or a video file."""
    path = Path(path)
    if path.is_dir():
        return the_session_video(path), path, pedals_gt_path(path)
    if not path.is_file():
        raise SessionError(f"{path} is neither a session folder nor a video file")
    session = session_of_video(path)
    if session is not None:
        return path, session, pedals_gt_path(session)
    return path, None, out_target(out if out is not None else path.with_name(path.stem + ".pedals_gt.csv"),
                                  inputs=(path,))


def run_ground_truth(request: GroundTruthRequest,
                     on_progress: Callable[[int, int], None] | None = None) -> GroundTruthResult:
    """Extract, debounce and write the pedal ground truth of one input."""
    layout = load_layout(request.layout)
    video, session_path, csv_path = resolve_input(request.input, request.out)
    if request.out is not None and session_path is not None:
        raise ConfigError("--out is for bare video files; a session's result always goes to derived/pedals_gt.csv")
    started = time.perf_counter()
    states = extract_pedal_states(video, layout, request.view, on_progress)
    states.states = debounce(states.states, request.min_duration)
    table, time_meta = _time_table(states, session_path)
    for j, pedal in enumerate(states.pedals):
        table[pedal] = states.states[:, j]
    meta = _meta(request, states, video, session_path, layout.describe(), time_meta)
    csv_path, json_path = write_pedals_gt(csv_path, table, meta)
    wall = time.perf_counter() - started
    fractions = {p: round(float(states.column(p).mean()), 4) for p in states.pedals}
    return GroundTruthResult(str(request.input), str(video), str(session_path) if session_path else None,
                             str(csv_path), str(json_path), len(states.states), states.video.fps, wall,
                             fractions, int(time_meta.get("frames_without_host_time", 0)))


def _time_table(states: PedalStates, session_path: Path | None) -> tuple[pd.DataFrame, dict[str, Any]]:
    """``frame`` plus the time column: t_host_ns from the session's video stream, else t_video_s."""
    frames = states.frames
    if session_path is None:
        fps = states.video.fps or float("nan")
        return pd.DataFrame({"frame": frames, "t_video_s": (frames / fps).round(6)}), {
            "time_column": "t_video_s: frame / container fps, seconds since the first frame (no session clock)"}
    stream, times = video_frame_times(Session.open(session_path))
    t_host = times.astype("Int64").reindex(frames).reset_index(drop=True)  # nullable: exact ns, no float
    missing = int(t_host.isna().sum())
    if stream is None or missing:
        log.warning("%s: %d of %d frames have no time in the session's video stream", session_path, missing,
                    len(frames))
    return pd.DataFrame({"frame": frames, "t_host_ns": t_host}), {
        "time_column": f"t_host_ns: host clock (Unix-epoch ns) of the row with seq = frame in stream {stream!r}"
                       if stream else "t_host_ns: empty, the session has no video stream",
        "video_stream": stream, "frames_without_host_time": missing}


def _meta(request: GroundTruthRequest, states: PedalStates, video: Path, session_path: Path | None,
          layout: dict[str, Any], time_meta: dict[str, Any]) -> dict[str, Any]:
    info = states.video
    source = str(video.resolve().relative_to(session_path.resolve())) if session_path else str(video.resolve())
    return {
        "original_scripts": ORIGINAL_NOTE, "source_video": source, **time_meta,
        "video": {"width": info.width, "height": info.height, "fps": info.fps, "fourcc": info.fourcc,
                  "frames_in_container": info.frame_count, "frames_decoded": int(len(states.states)),
                  "view": states.view, "view_size": list(states.view_size)},
        "layout": layout, "pedals": states.pedals, "min_duration_frames": request.min_duration,
        "values": "1 = pressed, 0 = released", "midas_version": __version__,
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }


