"""Write a synthetic da Vinci Xi console video (:mod:`midas_cli.synthetic.console_video`) and its pedal
schedule: frame i of the file shows schedule row i (0-based); lossy compression by the video writer.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pandas as pd

from midas_cli.analysis.pedal_video.detectors import load_template
from midas_cli.analysis.pedal_video.layout import Layout, load_layout
from midas_cli.errors import ConfigError, SessionError
from midas_cli.session.pedals_gt import write_pedals_gt
from midas_cli.synthetic.console_video import (REF_H, REF_W, REQUIRED_REGIONS, SCHEDULE_PEDALS, SHIFT_EVERY,
                                               ConsoleRenderer, ConsoleVideoSpec, finish_frame, make_schedule,
                                               right_slots, shift_frame, slot_colours)

CODECS = {".mkv": "mp4v", ".mp4": "mp4v", ".avi": "MJPG"}


@dataclass
class ConsoleVideo:
    video: Path
    schedule_csv: Path
    schedule_json: Path
    frames: int
    pedals: list[str]


def render_console_video(out_path: Path | str, spec: ConsoleVideoSpec,
                         on_progress: Callable[[int, int], None] | None = None) -> ConsoleVideo:
    """Write the video to ``out_path`` (.mkv/.mp4: MPEG-4 part 2 "mp4v"; .avi: MJPG) and its schedule to
    ``<stem>.schedule.csv`` + ``.json`` beside it (frame, one 0/1 column per pedal)."""
    out_path = Path(out_path)
    _check_spec(out_path, spec)
    layout = load_layout(spec.layout)
    rng = np.random.default_rng(spec.seed)
    schedule = make_schedule(_schedule_pedals(layout), layout.pedals["arm_swap"].hold_frames, spec.frames, rng)
    pressed = {p: schedule[:, j].astype(bool) for j, p in enumerate(layout.pedal_names)}
    right_slot = right_slots(pressed, rng)
    endoscope_slot = int(rng.integers(4))
    slot_blue = slot_colours(pressed["arm_swap"], endoscope_slot, rng)
    shifts = rng.integers(-spec.max_shift_px, spec.max_shift_px + 1, (spec.frames // SHIFT_EVERY + 1, 2))
    renderer = console_renderer(layout, rng, spec.noise_sigma)
    writer = _open_writer(out_path, spec)
    try:
        for i in range(spec.frames):
            frame = renderer.render(i, {p: bool(v[i]) for p, v in pressed.items()}, int(right_slot[i]), slot_blue[i],
                                    endoscope_slot)
            frame = shift_frame(frame, *shifts[i // SHIFT_EVERY])
            renderer.add_noise(frame, i)
            writer.write(finish_frame(frame, spec))
            if on_progress is not None and i % 30 == 0:
                on_progress(i + 1, spec.frames)
    finally:
        writer.release()
    table = pd.DataFrame(schedule, columns=layout.pedal_names)
    table.insert(0, "frame", np.arange(spec.frames, dtype=np.int64))
    meta = {"generator": "midas simulate console-video", **asdict(spec), "video": out_path.name,
            "codec": CODECS[out_path.suffix.lower()], "endoscope_slot": endoscope_slot + 1,
            "shift_every_frames": SHIFT_EVERY, "shifts_px": shifts.tolist(), "layout": layout.describe()}
    csv_path, json_path = write_pedals_gt(out_path.with_name(out_path.stem + ".schedule.csv"), table, meta)
    if on_progress is not None:
        on_progress(spec.frames, spec.frames)
    return ConsoleVideo(out_path, csv_path, json_path, spec.frames, layout.pedal_names)


def console_renderer(layout: Layout, rng: np.random.Generator, noise_sigma: float) -> ConsoleRenderer:
    """A renderer of ``layout``'s regions (the davinci-xi layout's), with its camera icon template."""
    missing = [r for r in REQUIRED_REGIONS if r not in layout.regions]
    if missing:
        raise ConfigError(f"layout {layout.name} lacks region(s) {', '.join(missing)} the generator draws")
    rects = {name: layout.regions[name].pixel_rect(REF_W, REF_H) for name in REQUIRED_REGIONS}
    return ConsoleRenderer(rects, load_template(layout.regions["camera_slot1"], layout), rng, noise_sigma)


def _schedule_pedals(layout: Layout) -> list[str]:
    """The layout's pedal names, checked to hold the pedals the generator draws."""
    missing = [p for p in SCHEDULE_PEDALS if p not in layout.pedal_names]
    if missing:
        raise ConfigError(f"the console-video generator draws the da Vinci Xi pedals; layout {layout.name} "
                          f"lacks {', '.join(missing)}")
    return layout.pedal_names


def _check_spec(out_path: Path, spec: ConsoleVideoSpec) -> None:
    if out_path.suffix.lower() not in CODECS:
        raise ConfigError(f"video {out_path} must end in {', '.join(CODECS)}")
    if spec.frames < 60 or spec.fps <= 0:
        raise ConfigError(f"need at least 60 frames (2 s at 30 fps), got {spec.frames} at {spec.fps} fps")
    if min(spec.size) < 64 or spec.max_shift_px < 0 or spec.noise_sigma < 0:
        raise ConfigError("size must be at least 64 px, shifts and noise non-negative")
    if not out_path.parent.is_dir():
        raise ConfigError(f"folder {out_path.parent} does not exist")


def _open_writer(out_path: Path, spec: ConsoleVideoSpec) -> cv2.VideoWriter:
    width, height = spec.size
    fourcc = CODECS[out_path.suffix.lower()]
    writer = cv2.VideoWriter(str(out_path), cv2.VideoWriter_fourcc(*fourcc), spec.fps,
                             (width * (2 if spec.stereo else 1), height))
    if not writer.isOpened():
        raise SessionError(f"this OpenCV build cannot write {fourcc} into {out_path.suffix} ({out_path})")
    return writer
