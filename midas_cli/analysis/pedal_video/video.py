"""Opening a console recording (MKV/MP4/AVI through cv2.VideoCapture) and cutting out the view.

Frames are numbered from 0 in decoding order: frame i is the (i+1)-th frame the container yields, the
same index as ``seq`` of the session's video stream. Side-by-side stereo recordings hold two views; the
layout's coordinates refer to one of them ("left"), a single-view recording is used whole ("full").
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from midas_cli.errors import ConfigError, SessionError

VIEW_CHOICES = ("auto", "left", "full")
STEREO_MIN_ASPECT = 2.5  # width / height above which "auto" takes a frame as side-by-side stereo


@dataclass(frozen=True)
class VideoInfo:
    """Container facts: frame size (px), nominal rate (Hz), frame count (0 when the container lacks it)."""

    path: Path
    width: int
    height: int
    fps: float
    frame_count: int
    fourcc: str


def open_video(path: Path | str) -> tuple[cv2.VideoCapture, VideoInfo]:
    """Open a recording; SessionError when it does not exist or no decoder reads it."""
    path = Path(path)
    if not path.is_file():
        raise SessionError(f"video {path} does not exist")
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise SessionError(f"cannot decode {path}: OpenCV's FFmpeg backend does not open it "
                           f"(is it a complete MKV/MP4/AVI file?)")
    code = int(capture.get(cv2.CAP_PROP_FOURCC))
    fourcc = "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4)).strip("\0")
    info = VideoInfo(path, int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                     float(capture.get(cv2.CAP_PROP_FPS) or 0.0), max(0, int(capture.get(cv2.CAP_PROP_FRAME_COUNT))),
                     fourcc)
    return capture, info


def resolve_view(view: str, width: int, height: int) -> str:
    """"left" or "full" for a frame of ``width`` x ``height``; "auto" picks "left" for side-by-side."""
    if view not in VIEW_CHOICES:
        raise ConfigError(f"view {view!r} unknown; expected one of {', '.join(VIEW_CHOICES)}")
    if view == "auto":
        return "left" if width / max(1, height) >= STEREO_MIN_ASPECT else "full"
    return view


def view_size(view: str, width: int, height: int) -> tuple[int, int]:
    """(width, height) of the resolved view inside a ``width`` x ``height`` frame."""
    return (width // 2, height) if view == "left" else (width, height)


def cut_view(frame: np.ndarray, view: str) -> np.ndarray:
    """The view's pixels of a decoded frame (a slice, no copy)."""
    return frame[:, : frame.shape[1] // 2] if view == "left" else frame


def iter_frames(capture: cv2.VideoCapture, stop: int | None = None,
                wanted: "set[int] | None" = None) -> Iterator[tuple[int, np.ndarray | None]]:
    """(index, BGR frame) in decoding order from 0 up to ``stop`` (exclusive, None = to the end).

    Every frame is grabbed (decoded); only frames in ``wanted`` (None = all) are converted to BGR, the
    others yield None, which saves the colour conversion of frames nobody looks at.
    """
    index = 0
    while (stop is None or index < stop) and capture.grab():
        if wanted is None or index in wanted:
            ok, frame = capture.retrieve()
            if not ok:
                raise SessionError(f"frame {index} could not be decoded")
            yield index, frame
        else:
            yield index, None
        index += 1
