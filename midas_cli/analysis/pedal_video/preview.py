"""A picture for checking a layout: one frame's view with every region outlined and its state written.

Green outline = region on, red = off, each with its name and score on a box of that colour; a panel
in the top-left corner lists each pedal's state. Tiny regions (single pixels) are outlined with a
margin so they can be found on the picture.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from midas_cli.analysis.pedal_video.layout import Layout
from midas_cli.analysis.pedal_video.reader import FrameReader, FrameReading
from midas_cli.analysis.pedal_video.video import cut_view, iter_frames, open_video, resolve_view, view_size
from midas_cli.errors import ConfigError, SessionError
from midas_cli.session.outputs import out_target, write_bytes

ON, OFF, TEXT = (60, 220, 60), (40, 40, 230), (255, 255, 255)
MIN_OUTLINE_PX = 8
FONT = cv2.FONT_HERSHEY_SIMPLEX


def preview_frame(video_path: Path | str, layout: Layout, frame_index: int,
                  view: str = "auto") -> tuple[np.ndarray, FrameReading]:
    """The annotated view (H, W, 3) BGR of frame ``frame_index`` (0-based) and what was read there.

    Stateful layouts (baseline detectors, swap rules) are evaluated on every frame up to the one asked
    for, so the picture shows what extraction reports for that frame; otherwise earlier frames are only
    decoded, not converted.
    """
    if frame_index < 0:
        raise ConfigError(f"preview frame must be >= 0, got {frame_index}")
    capture, info = open_video(video_path)
    try:
        resolved = resolve_view(view, info.width, info.height)
        reader = FrameReader(layout, view_size(resolved, info.width, info.height))
        wanted = None if reader.stateful else {frame_index}
        reading, picture = None, None
        for index, frame in iter_frames(capture, stop=frame_index + 1, wanted=wanted):  # noqa: B007 - read after
            if frame is not None:
                picture = cut_view(frame, resolved)
                reading = reader.read(picture)
    finally:
        capture.release()
    if reading is None or picture is None or index != frame_index:
        raise SessionError(f"{video_path} has no frame {frame_index} (frames are numbered from 0)")
    return draw_reading(picture.copy(), reader, reading), reading


def draw_reading(picture: np.ndarray, reader: FrameReader, reading: FrameReading) -> np.ndarray:
    """Outline and label every region of ``reader`` on ``picture`` (modified and returned).

    Text scales with the frame (about 22 px tall labels at 1080p, never under 12 px) and is written in
    white or black on a filled box of the region's state colour, so it reads on any background."""
    scale = text_scale(picture.shape[0])
    thickness = max(1, round(scale * 1.5))
    placed: list[tuple[int, int, int, int]] = []
    for name, (x, y, w, h) in reader.rects.items():
        state, score = reading.regions[name]
        pad = max(0, (MIN_OUTLINE_PX - min(w, h)) // 2)
        colour = ON if state else OFF
        cv2.rectangle(picture, (x - pad - 1, y - pad - 1), (x + w + pad, y + h + pad), colour, thickness)
        label = f"{name} {score:.2f}"
        (tw, th), base = cv2.getTextSize(label, FONT, scale * 0.8, thickness)
        left = min(max(0, x - pad), picture.shape[1] - tw - 7)  # kept inside the frame
        box = _free_spot(placed, left, y - pad - 4, tw + 6, th + base + 6)
        _label(picture, label, box, colour, scale * 0.8, thickness)
    lines = [f"{pedal}: {'PRESSED' if on else 'released'}" for pedal, on in reading.pedals.items()]
    (_, th), base = cv2.getTextSize("Xg", FONT, scale, thickness)
    line_h = th + base + 8
    widest = max((cv2.getTextSize(line, FONT, scale, thickness)[0][0] for line in lines), default=0)
    cv2.rectangle(picture, (0, 0), (widest + 16, line_h * len(lines) + 8), (0, 0, 0), -1)
    for i, (line, on) in enumerate(zip(lines, reading.pedals.values())):
        cv2.putText(picture, line, (8, line_h * (i + 1)), FONT, scale, ON if on else TEXT, thickness, cv2.LINE_AA)
    return picture


def text_scale(height: int) -> float:
    """OpenCV font scale for a frame ``height`` px tall: ~22 px capitals at 1080p, at least ~12 px."""
    return max(0.55, height / 1080 * 1.0)


def _label(picture: np.ndarray, text: str, box: tuple[int, int, int, int], colour: tuple[int, int, int],
           scale: float, thickness: int) -> None:
    """``text`` on a filled box of ``colour`` (black ink on light colours, white on dark)."""
    x, y, w, h = box
    cv2.rectangle(picture, (x, y - h), (x + w, y), colour, -1)
    ink = (0, 0, 0) if sum(colour) > 3 * 128 else TEXT
    cv2.putText(picture, text, (x + 3, y - 4 - (h - 6) // 5), FONT, scale, ink, thickness, cv2.LINE_AA)


def _free_spot(placed: list[tuple[int, int, int, int]], x: int, y: int, w: int, h: int) -> tuple[int, int, int, int]:
    """A label box (x, baseline y, w, h) moved up until it overlaps no label placed before; recorded."""
    while any(x < px + pw and px < x + w and y - h < py and py - ph < y for px, py, pw, ph in placed):
        y -= h
    placed.append((x, y, w, h))
    return x, y, w, h


def write_png(path: Path | str, picture: np.ndarray) -> Path:
    """Write ``picture`` as PNG; ConfigError when the path cannot be written."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ConfigError(f"preview output {path} must end in .png")
    ok, encoded = cv2.imencode(".png", picture)
    if not ok:
        raise ConfigError(f"cannot encode the preview {path} as PNG")
    return write_bytes(out_target(path), encoded.tobytes())
