"""The endoscope recording of a LeRobot episode: recording frames copied to an MP4 on the episode's
constant-rate clock (MPEG-4 part 2 through OpenCV, which midas already uses), with LeRobot's feature
entry and per-channel stats for it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.errors import SessionError

STATS_VIDEO_FRAMES = 200  # frames sampled for the video's per-channel stats


def write_video(source: Path, frames: np.ndarray, fps: int, target: Path) -> dict[str, Any]:
    """Copy recording frames ``frames`` (ascending) of ``source`` to ``target`` (.mp4, constant ``fps``);
    returns the LeRobot feature of the video and its stats (per RGB channel, in [0, 1], from up to
    STATS_VIDEO_FRAMES frames). SessionError when the recording cannot be read or lacks a frame."""
    import cv2

    capture = cv2.VideoCapture(str(source))
    if not capture.isOpened():
        raise SessionError(f"cannot read the video recording {source}")
    writer, position, pixels = None, 0, ChannelStats()
    every = max(1, len(frames) // STATS_VIDEO_FRAMES)
    try:
        for row, wanted in enumerate(frames.tolist()):
            if wanted < position:
                raise SessionError(f"aligned frames are not ascending at row {row} (frame {wanted}): "
                                   f"re-run `midas align`")
            while position <= wanted:
                ok, image = capture.read()
                if not ok:
                    raise SessionError(f"{source} ends after {position} frames; the aligned table needs frame {wanted}")
                position += 1
            if writer is None:
                writer = cv2.VideoWriter(str(target), cv2.VideoWriter_fourcc(*"mp4v"), fps, image.shape[1::-1])
            writer.write(image)
            if row % every == 0:
                pixels.add(image[:, :, ::-1].reshape(-1, 3))  # BGR -> RGB
    finally:
        capture.release()
        if writer is not None:
            writer.release()
    height, width = image.shape[:2]
    feature = {"dtype": "video", "shape": [height, width, 3], "names": ["height", "width", "channels"],
               "info": {"video.height": height, "video.width": width, "video.codec": "mpeg4",
                        "video.pix_fmt": "yuv420p", "video.is_depth_map": False, "video.fps": fps,
                        "video.channels": 3, "has_audio": False}}
    return {"feature": feature, "stats": pixels.stats()}


class ChannelStats:
    """Per-channel min, max, mean and std of 8-bit pixels added a frame at a time (LeRobot's image stats:
    shape (3, 1, 1), in [0, 1]; ``count`` = frames added). Only running sums are kept."""

    def __init__(self) -> None:
        self.frames, self.pixels = 0, 0
        self.total, self.squares = np.zeros(3), np.zeros(3)
        self.low, self.high = np.full(3, 255.0), np.zeros(3)

    def add(self, pixels: np.ndarray) -> None:
        """One frame's (P, 3) uint8 pixels, RGB."""
        values = pixels.astype(np.float64)
        self.frames, self.pixels = self.frames + 1, self.pixels + len(values)
        self.total += values.sum(axis=0)
        self.squares += (values ** 2).sum(axis=0)
        self.low, self.high = np.minimum(self.low, values.min(axis=0)), np.maximum(self.high, values.max(axis=0))

    def stats(self) -> dict[str, np.ndarray]:
        mean = self.total / self.pixels
        std = np.sqrt(np.maximum(self.squares / self.pixels - mean ** 2, 0.0))
        shaped = {"min": self.low, "max": self.high, "mean": mean, "std": std}
        return {**{k: (v / 255.0).reshape(3, 1, 1) for k, v in shaped.items()}, "count": np.array([self.frames])}
