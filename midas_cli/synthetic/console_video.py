"""Frames of a synthetic da Vinci Xi surgeon-console video whose pedal indicators follow a known, seeded
schedule.

The picture: an endoscope-like tissue background drifting slowly, two instrument shafts moving over it,
and the console's bottom UI band drawn at the places the layout reads (energy indicators, instrument
slots with arm colours and icons, the clutch icon). On top: sensor noise, occasional whole-frame shifts of
up to ``max_shift_px`` pixels (capture jitter), optional down-scaling and side-by-side stereo. Writing the
video file and its schedule (and reading the layout) is :mod:`midas_cli.simulate.console_video`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

REF_W, REF_H = 1920, 1080
LEFT_ENERGY = ("secondary_energy_left", "primary_energy_left")
RIGHT_ENERGY = ("secondary_energy_right", "primary_energy_right")
SCHEDULE_PEDALS = (*LEFT_ENERGY, *RIGHT_ENERGY, "clutch", "camera", "arm_swap")
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


def make_schedule(pedal_names: list[str], arm_swap_hold_frames: int, frames: int, rng: np.random.Generator,
                  lead_in: int = 45) -> np.ndarray:
    """(frames, P) uint8 true pedal states, columns = ``pedal_names`` (which must hold ``SCHEDULE_PEDALS``).

    Energy pedals on one side never overlap (one pedal, one indicator); arm-swap presses last
    ``arm_swap_hold_frames``; nothing is pressed during the first ``lead_in`` frames (baseline detectors learn
    the released look there).
    """
    names = list(pedal_names)
    states = np.zeros((frames, len(names)), dtype=np.uint8)
    hold = arm_swap_hold_frames
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
    """Draws reference-size (1920 x 1080) console frames.

    ``rects``: (x, y, w, h) reference-size pixel rectangles of every region in ``REQUIRED_REGIONS`` (the
    davinci-xi layout's); ``camera_icon``: the greyscale camera icon drawn into the endoscope's slot.
    """

    def __init__(self, rects: dict[str, tuple[int, int, int, int]], camera_icon: np.ndarray,
                 rng: np.random.Generator, noise_sigma: float) -> None:
        self.rect = {name: rects[name] for name in REQUIRED_REGIONS}
        self.camera_icon = camera_icon
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


def shift_frame(frame: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """``frame`` moved by (dx, dy) pixels (right/down positive), edges repeated."""
    if dx == 0 and dy == 0:
        return frame
    height, width = frame.shape[:2]
    kept = frame[max(0, -dy):height - max(0, dy), max(0, -dx):width - max(0, dx)]
    return cv2.copyMakeBorder(kept, max(0, dy), max(0, -dy), max(0, dx), max(0, -dx), cv2.BORDER_REPLICATE)


def finish_frame(frame: np.ndarray, spec: ConsoleVideoSpec) -> np.ndarray:
    """Scale the reference frame to the view size; put a right view (8 px disparity) beside it if stereo."""
    if spec.size != (REF_W, REF_H):
        frame = cv2.resize(frame, spec.size, interpolation=cv2.INTER_AREA)
    if not spec.stereo:
        return frame
    right = np.concatenate([frame[:, 8:], frame[:, -8:]], axis=1)
    return np.concatenate([frame, right], axis=1)


def right_slots(pressed: dict[str, np.ndarray], rng: np.random.Generator) -> np.ndarray:
    """Per frame, which right instrument (1 or 2) shows the right energy; redrawn at every press."""
    active = pressed[RIGHT_ENERGY[0]] | pressed[RIGHT_ENERGY[1]]
    onsets = np.flatnonzero(np.diff(active.astype(np.int8), prepend=0) == 1)
    slots = np.ones(len(active), dtype=np.int8)
    for start, end in zip(onsets, np.r_[onsets[1:], len(active)]):
        slots[start:end] = rng.integers(1, 3)
    return slots


def slot_colours(swap: np.ndarray, endoscope_slot: int, rng: np.random.Generator) -> np.ndarray:
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
