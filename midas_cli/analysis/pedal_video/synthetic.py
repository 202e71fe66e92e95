"""A synthetic da Vinci Xi surgeon-console video whose pedal indicators follow a known, seeded schedule.

The picture: an endoscope-like tissue background drifting slowly, two instrument shafts moving over it,
and the console's bottom UI band drawn at the places the layout reads (energy indicators, instrument
slots with arm colours and icons, the clutch icon). On top: sensor noise, occasional whole-frame shifts of
up to ``max_shift_px`` pixels (capture jitter), optional down-scaling, side-by-side stereo, and lossy
compression by the video writer. Frame i of the file shows schedule row i (0-based).
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

REF_W, REF_H = 1920, 1080
CODECS = {".mkv": "mp4v", ".mp4": "mp4v", ".avi": "MJPG"}
LEFT_ENERGY = ("secondary_energy_left", "primary_energy_left")
RIGHT_ENERGY = ("secondary_energy_right", "primary_energy_right")
REQUIRED_REGIONS = ("left_cut", "right1_cut", "right2_cut", "clutch_icon",
                    *(f"camera_slot{i}" for i in range(1, 5)), *(f"arm_slot{i}" for i in range(1, 5)))
YELLOW, BLUE, ENERGY_OFF = (20, 200, 235), (235, 140, 20), (70, 70, 70)
SLOT_BLUE, SLOT_BLACK, TILE = (200, 120, 30), (15, 15, 15), (30, 30, 30)
CLUTCH_ON, CLUTCH_OFF = (235, 235, 235), (90, 90, 90)
SHIFT_EVERY = 60  # frames between changes of the whole-frame shift
ARM_ICON = [".........", ".#.....#.", "..#...#..", "...#.#...", "....#....", "....#....", "....#....",
            "...###...", "........."]
# (gap low, gap high, press low, press high) in frames, per pedal group
TIMING = {"energy": (20, 120, 6, 60), "clutch": (30, 150, 10, 90), "camera": (30, 200, 15, 120),
          "arm_swap": (60, 300, 0, 0)}


@dataclass(frozen=True)
class ConsoleVideoSpec:
    """What to render: ``size`` is one view's (width, height) in pixels; ``fps`` in Hz."""

    duration_s: float
    seed: int = 0
    fps: float = 30.0
    size: tuple[int, int] = (REF_W, REF_H)
    stereo: bool = False
    noise_sigma: float = 3.0
    max_shift_px: int = 1
    layout: str = "davinci-xi"

    @property
    def frames(self) -> int:
        return int(round(self.duration_s * self.fps))


@dataclass
class ConsoleVideo:
    video: Path
    schedule_csv: Path
    schedule_json: Path
    frames: int
    pedals: list[str]


def make_schedule(layout: Layout, frames: int, rng: np.random.Generator, lead_in: int = 45) -> np.ndarray:
    """(frames, P) uint8 true pedal states, columns = ``layout.pedal_names``.

    Energy pedals on one side never overlap (one pedal, one indicator); arm-swap presses last the layout's
    ``hold_frames``; nothing is pressed during the first ``lead_in`` frames (baseline detectors learn
    the released look there).
    """
    names = layout.pedal_names
    missing = [p for p in (*LEFT_ENERGY, *RIGHT_ENERGY, "clutch", "camera", "arm_swap") if p not in names]
    if missing:
        raise ConfigError(f"the console-video generator draws the da Vinci Xi pedals; layout {layout.name} "
                          f"lacks {', '.join(missing)}")
    states = np.zeros((frames, len(names)), dtype=np.uint8)
    hold = layout.pedals["arm_swap"].hold_frames
    groups = [(LEFT_ENERGY, "energy"), (RIGHT_ENERGY, "energy"), (("clutch",), "clutch"),
              (("camera",), "camera"), (("arm_swap",), "arm_swap")]
    for pedals, timing in groups:
        gap_lo, gap_hi, press_lo, press_hi = TIMING[timing]
        t = lead_in + int(rng.integers(0, gap_lo))
        while True:
            length = hold if timing == "arm_swap" else int(rng.integers(press_lo, press_hi + 1))
            if t + length >= frames:
                break
            states[t:t + length, names.index(pedals[int(rng.integers(len(pedals)))])] = 1
            t += length + int(rng.integers(max(gap_lo, hold + 2 if timing == "arm_swap" else gap_lo), gap_hi + 1))
    return states


class ConsoleRenderer:
    """Draws reference-size (1920 x 1080) console frames for the davinci-xi layout's regions."""

    def __init__(self, layout: Layout, rng: np.random.Generator, noise_sigma: float) -> None:
        missing = [r for r in REQUIRED_REGIONS if r not in layout.regions]
        if missing:
            raise ConfigError(f"layout {layout.name} lacks region(s) {', '.join(missing)} the generator draws")
        self.rect = {name: layout.regions[name].pixel_rect(REF_W, REF_H) for name in REQUIRED_REGIONS}
        self.camera_icon = load_template(layout.regions["camera_slot1"], layout)
        self.arm_icon = np.array([[235 if c == "#" else TILE[0] for c in row] for row in ARM_ICON], np.uint8)
        self.texture = tissue_texture(rng, REF_H + 80, REF_W + 80)
        self.noise = [_noise_pair(rng, noise_sigma) for _ in range(4)] if noise_sigma > 0 else []
        self.band_top = min(y for _, y, _, _ in self.rect.values()) - 14

    def render(self, index: int, pressed: dict[str, bool], right_slot: int, slot_blue: np.ndarray,
               endoscope_slot: int) -> np.ndarray:
        """One 1080 x 1920 x 3 BGR frame (before shift and noise)."""
        ox, oy = (40 + 38 * np.sin(index / 97.0 + np.array([0.0, 1.3]))).astype(int)
        frame = self.texture[oy:oy + REF_H, ox:ox + REF_W].copy()
        _instruments(frame, index)
        frame[self.band_top:REF_H - 4] = (frame[self.band_top:REF_H - 4] // 6 + 22)
        self._energy(frame, pressed, right_slot)
        self._slots(frame, pressed["camera"], slot_blue, endoscope_slot)
        x, y, w, h = self.rect["clutch_icon"]
        cv2.rectangle(frame, (x - 4, y - 4), (x + w + 3, y + h + 3), CLUTCH_ON if pressed["clutch"] else CLUTCH_OFF, -1)
        return frame

    def add_noise(self, frame: np.ndarray, index: int) -> None:
        if self.noise:
            positive, negative = self.noise[index % len(self.noise)]
            cv2.add(frame, positive, dst=frame)
            cv2.subtract(frame, negative, dst=frame)

    def _energy(self, frame: np.ndarray, pressed: dict[str, bool], right_slot: int) -> None:
        left = YELLOW if pressed[LEFT_ENERGY[0]] else BLUE if pressed[LEFT_ENERGY[1]] else ENERGY_OFF
        right = YELLOW if pressed[RIGHT_ENERGY[0]] else BLUE if pressed[RIGHT_ENERGY[1]] else ENERGY_OFF
        for name, colour, label in (("left_cut", left, "L"), ("right1_cut", right if right_slot == 1 else ENERGY_OFF,
                                     "R1"), ("right2_cut", right if right_slot == 2 else ENERGY_OFF, "R2")):
            x, y, _, _ = self.rect[name]
            cv2.rectangle(frame, (x - 45, y - 12), (x + 45, y + 12), colour, -1)
            cv2.putText(frame, label, (x - 10, y + 36), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (200, 200, 200), 1, cv2.LINE_AA)

    def _slots(self, frame: np.ndarray, camera: bool, slot_blue: np.ndarray, endoscope_slot: int) -> None:
        for i in range(4):
            ax, ay, aw, ah = self.rect[f"arm_slot{i + 1}"]
            cx, cy, _, _ = self.rect[f"camera_slot{i + 1}"]
            cv2.rectangle(frame, (ax - 6, ay - 4), (cx + 14, ay + ah + 3), TILE, -1)
            cv2.rectangle(frame, (ax - 4, ay - 4), (ax + aw - 2, ay + ah + 3),
                          SLOT_BLUE if slot_blue[i] else SLOT_BLACK, -1)
            icon = self.camera_icon if camera and i == endoscope_slot else self.arm_icon
            frame[cy + 1:cy + 1 + icon.shape[0], cx + 1:cx + 1 + icon.shape[1]] = icon[:, :, None]


def tissue_texture(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """An endoscope-like (H, W, 3) BGR picture: pink-red tissue, vessels, highlights, vignette."""
    def smooth(cell: int) -> np.ndarray:
        small = rng.normal(0, 1, (height // cell + 2, width // cell + 2)).astype(np.float32)
        return cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
    field = 0.6 * smooth(160) + 0.3 * smooth(40) + 0.1 * smooth(8)
    image = np.stack([55 + 18 * field, 65 + 22 * field, 165 + 40 * field], axis=2)
    for _ in range(25):
        angles = rng.uniform(0, 2 * np.pi) + np.cumsum(rng.normal(0, 0.25, 40))
        steps = 15 * np.stack([np.cos(angles), np.sin(angles)], axis=1)
        points = np.cumsum(steps, axis=0) + rng.uniform((0, 0), (width, height))
        cv2.polylines(image, [points.astype(np.int32)], False, (40, 35, 115), int(rng.integers(2, 6)), cv2.LINE_AA)
    for _ in range(30):
        centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        cv2.ellipse(image, centre, (int(rng.integers(3, 14)), int(rng.integers(2, 8))), float(rng.uniform(0, 180)),
                    0, 360, (250, 250, 255), -1)
    image = cv2.GaussianBlur(image, (0, 0), 1.5)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    radius = np.hypot((xx - width / 2) / (width / 2), (yy - height / 2) / (height / 2))
    image *= np.clip(1.15 - 0.55 * radius ** 2, 0.25, 1.0)[:, :, None]
    return np.clip(image, 0, 255).astype(np.uint8)


def _instruments(frame: np.ndarray, index: int) -> None:
    for side, phase in ((0, 0.0), (1, 2.1)):
        tip = (int(REF_W * (0.38 + 0.24 * side) + 160 * np.sin(index / 45.0 + phase)),
               int(REF_H * 0.45 + 120 * np.cos(index / 61.0 + phase)))
        base = (-100 if side == 0 else REF_W + 100, REF_H + 50)
        cv2.line(frame, base, tip, (150, 155, 160), 46, cv2.LINE_AA)
        cv2.line(frame, base, tip, (205, 210, 215), 10, cv2.LINE_AA)


def _noise_pair(rng: np.random.Generator, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    noise = rng.standard_normal((REF_H, REF_W, 3), dtype=np.float32)
    noise *= sigma
    return cv2.convertScaleAbs(np.maximum(noise, 0)), cv2.convertScaleAbs(np.maximum(-noise, 0))


def render_console_video(out_path: Path | str, spec: ConsoleVideoSpec,
                         on_progress: Callable[[int, int], None] | None = None) -> ConsoleVideo:
    """Write the video to ``out_path`` (.mkv/.mp4: MPEG-4 part 2 "mp4v"; .avi: MJPG) and its schedule to
    ``<stem>.schedule.csv`` + ``.json`` beside it (frame, one 0/1 column per pedal)."""
    out_path = Path(out_path)
    _check_spec(out_path, spec)
    layout = load_layout(spec.layout)
    rng = np.random.default_rng(spec.seed)
    schedule = make_schedule(layout, spec.frames, rng)
    pressed = {p: schedule[:, j].astype(bool) for j, p in enumerate(layout.pedal_names)}
    right_slot = _right_slots(pressed, rng)
    endoscope_slot = int(rng.integers(4))
    slot_blue = _slot_colours(pressed["arm_swap"], endoscope_slot, rng)
    shifts = rng.integers(-spec.max_shift_px, spec.max_shift_px + 1, (spec.frames // SHIFT_EVERY + 1, 2))
    renderer = ConsoleRenderer(layout, rng, spec.noise_sigma)
    writer = _open_writer(out_path, spec)
    try:
        for i in range(spec.frames):
            frame = renderer.render(i, {p: bool(v[i]) for p, v in pressed.items()}, int(right_slot[i]), slot_blue[i],
                                    endoscope_slot)
            frame = shift_frame(frame, *shifts[i // SHIFT_EVERY])
            renderer.add_noise(frame, i)
            writer.write(_finish(frame, spec))
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


def shift_frame(frame: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """``frame`` moved by (dx, dy) pixels (right/down positive), edges repeated."""
    if dx == 0 and dy == 0:
        return frame
    height, width = frame.shape[:2]
    kept = frame[max(0, -dy):height - max(0, dy), max(0, -dx):width - max(0, dx)]
    return cv2.copyMakeBorder(kept, max(0, dy), max(0, -dy), max(0, dx), max(0, -dx), cv2.BORDER_REPLICATE)


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


def _finish(frame: np.ndarray, spec: ConsoleVideoSpec) -> np.ndarray:
    """Scale the reference frame to the view size; put a right view (8 px disparity) beside it if stereo."""
    if spec.size != (REF_W, REF_H):
        frame = cv2.resize(frame, spec.size, interpolation=cv2.INTER_AREA)
    if not spec.stereo:
        return frame
    right = np.concatenate([frame[:, 8:], frame[:, -8:]], axis=1)
    return np.concatenate([frame, right], axis=1)


def _right_slots(pressed: dict[str, np.ndarray], rng: np.random.Generator) -> np.ndarray:
    """Per frame, which right instrument (1 or 2) shows the right energy; redrawn at every press."""
    active = pressed[RIGHT_ENERGY[0]] | pressed[RIGHT_ENERGY[1]]
    onsets = np.flatnonzero(np.diff(active.astype(np.int8), prepend=0) == 1)
    slots = np.ones(len(active), dtype=np.int8)
    for start, end in zip(onsets, np.r_[onsets[1:], len(active)]):
        slots[start:end] = rng.integers(1, 3)
    return slots


def _slot_colours(swap: np.ndarray, endoscope_slot: int, rng: np.random.Generator) -> np.ndarray:
    """(frames, 4) bool, True = blue: two instrument slots driven by the hands; every swap onset trades
    one blue slot for the idle black one (the endoscope's slot stays black)."""
    instruments = [i for i in range(4) if i != endoscope_slot]
    blue = np.zeros(4, dtype=bool)
    blue[instruments[:2]] = True
    colours = np.zeros((len(swap), 4), dtype=bool)
    onsets = set(np.flatnonzero(np.diff(swap.astype(np.int8), prepend=0) == 1).tolist())
    for i in range(len(swap)):
        if i in onsets:
            idle = next(s for s in instruments if not blue[s])
            busy = [s for s in instruments if blue[s]]
            blue[busy[int(rng.integers(2))]], blue[idle] = False, True
        colours[i] = blue
    return colours
