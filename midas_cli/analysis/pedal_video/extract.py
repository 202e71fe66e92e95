"""Pedal states of every frame of a console recording, and debouncing of the result."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from midas_cli.analysis.pedal_video.layout import Layout
from midas_cli.analysis.pedal_video.reader import FrameReader
from midas_cli.analysis.pedal_video.video import (VideoInfo, cut_view, iter_frames, open_video, resolve_view,
                                                  view_size)
from midas_cli.errors import ConfigError, SessionError

log = logging.getLogger(__name__)

ProgressCallback = Callable[[int, int], None]  # (frames done, frames expected; 0 = unknown)
PROGRESS_EVERY = 30  # frames between progress callbacks


@dataclass
class PedalStates:
    """``states`` (N, P) uint8, 1 = pressed, row i = video frame i (0-based); columns = ``pedals``."""

    pedals: list[str]
    states: np.ndarray
    video: VideoInfo
    view: str
    view_size: tuple[int, int]

    @property
    def frames(self) -> np.ndarray:
        return np.arange(len(self.states), dtype=np.int64)

    def column(self, pedal: str) -> np.ndarray:
        return self.states[:, self.pedals.index(pedal)]


def extract_pedal_states(video_path: Path | str, layout: Layout, view: str = "auto",
                         on_progress: ProgressCallback | None = None) -> PedalStates:
    """Decode ``video_path`` frame by frame and read the layout's pedals from each frame's view."""
    capture, info = open_video(video_path)
    try:
        resolved = resolve_view(view, info.width, info.height)
        size = view_size(resolved, info.width, info.height)
        reader = FrameReader(layout, size)
        rows: list[list[bool]] = []
        for index, frame in iter_frames(capture):
            rows.append(list(reader.read(cut_view(frame, resolved)).pedals.values()))
            if on_progress is not None and index % PROGRESS_EVERY == 0:
                on_progress(index + 1, info.frame_count)
    finally:
        capture.release()
    if not rows:
        raise SessionError(f"{video_path} holds no decodable frames")
    if info.frame_count and info.frame_count != len(rows):
        log.warning("%s: container says %d frames, %d decoded", video_path, info.frame_count, len(rows))
    if on_progress is not None:
        on_progress(len(rows), len(rows))
    states = np.asarray(rows, dtype=np.uint8).reshape(len(rows), len(layout.pedals))
    return PedalStates(layout.pedal_names, states, info, resolved, size)


def debounce(states: np.ndarray, min_frames: int) -> np.ndarray:
    """Drop state changes that do not last ``min_frames`` frames: such a run takes the state before it.

    ``states`` (N,) or (N, P) of 0/1; applied per column. Works offline, so accepted changes keep their
    original frame (no added lag). The first run is always kept.
    """
    if min_frames < 1:
        raise ConfigError(f"minimum duration must be >= 1 frame, got {min_frames}")
    if states.ndim == 2:
        return np.stack([debounce(states[:, j], min_frames) for j in range(states.shape[1])], axis=1) \
            if states.shape[1] else states.copy()
    result = states.copy()
    if min_frames == 1 or len(result) == 0:
        return result
    edges = np.flatnonzero(np.diff(states)) + 1
    starts, ends = np.r_[0, edges], np.r_[edges, len(states)]
    for start, end in zip(starts[1:], ends[1:]):
        if end - start < min_frames:
            result[start:end] = result[start - 1]
    return result
