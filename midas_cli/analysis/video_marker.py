"""The OBS sync marker in the pixels: the true offset between video frame times and the host clock.

``midas record`` with ``obs://...?marker=SOURCE`` shows a scene item at known host times (stream
``<video>_marker``: t_host_ns before the request, t_ack_ns after OBS answered, enabled 1/0). The first
frame that shows it was composed at or after the request, so ``t_host_ns(frame) - t_toggle`` is the
error of the video stream's frame times plus up to one frame interval of render wait. Pure functions on
arrays, plus one reader that decodes a region of every frame with OpenCV.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from midas_cli.errors import ConfigError, SessionError

EARLY_WINDOW_NS = 1_000_000_000  # an onset this much before the request still belongs to it (frame times may run early)


def region_brightness(video: Path, roi: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Mean grey level (0..255) of ``roi`` = (x, y, width, height) pixels, or the whole frame, for every
    frame of ``video`` in decoding order; shape (frames,)."""
    import cv2

    capture = cv2.VideoCapture(str(video))
    if not capture.isOpened():
        raise SessionError(f"cannot open video {video} (missing, or not a format OpenCV's FFmpeg reads)")
    values = []
    try:
        while True:
            ok, frame = capture.read()  # (H, W, 3) uint8 BGR
            if not ok:
                break
            if roi is not None:
                x, y, w, h = roi
                frame = frame[y:y + h, x:x + w]
            values.append(float(frame.mean()))
    finally:
        capture.release()
    return np.asarray(values)


def marker_onsets(brightness: np.ndarray, min_contrast: float = 40.0) -> np.ndarray:
    """Frame indices where the marker appears: brightness rises through the midpoint of its range.
    ``min_contrast`` (grey levels) is the least range that counts as a marker at all; (onsets,)."""
    if brightness.size < 2:
        return np.zeros(0, dtype=np.int64)
    low, high = float(np.min(brightness)), float(np.max(brightness))
    if high - low < min_contrast:
        raise ConfigError(f"the marker region changes by only {high - low:.1f} grey levels (need {min_contrast}): "
                          f"is the region right and was the marker shown during the recording?")
    shown = brightness > (low + high) / 2
    return np.flatnonzero(shown[1:] & ~shown[:-1]) + 1


def marker_offsets_ms(frame_t_host_ns: np.ndarray, onset_frames: np.ndarray, shown_at_ns: np.ndarray) -> np.ndarray:
    """For each showing (host time of the request, (K,) ascending), the first onset frame from
    ``EARLY_WINDOW_NS`` before it up to the next showing: ``t_host_ns(frame) - shown_at`` in ms, NaN where
    there is none. ``frame_t_host_ns`` (N,) indexed by frame; ``onset_frames`` from ``marker_onsets``."""
    onset_times = frame_t_host_ns[onset_frames]
    offsets = np.full(len(shown_at_ns), np.nan)
    for k, shown in enumerate(shown_at_ns):
        limit = shown_at_ns[k + 1] if k + 1 < len(shown_at_ns) else np.iinfo(np.int64).max
        candidates = onset_times[(onset_times >= shown - EARLY_WINDOW_NS) & (onset_times < limit)]
        if candidates.size:
            offsets[k] = (int(candidates[0]) - int(shown)) / 1e6
    return offsets
