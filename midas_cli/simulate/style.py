"""How hard a simulated dataset is: per-subject style and per-session sensor placement (``--difficulty``).

``easy``: every subject moves the same way (the generator before issue 19): a model that has seen some
subjects recognises the others almost perfectly. ``real`` (the default): the ways real data is hard.

* Subject style (drawn from (seed, subject id) only, so a subject is the same person in every trial):
  speed (gesture durations / speed, faster moves), amplitude (scale of every gesture's reach), a
  personal bias of each gesture's target pose per hand (style), consistency (trial-to-trial spread),
  handedness (left-handed subjects swap the hands' roles, mirrored), how gestures start and end (the
  motion boundaries lead or lag the label boundaries by a personal mean plus per-boundary jitter),
  blending (the move towards the next gesture starts before the label switches), tremor and fine-motion
  scale, and how often the subject pauses and how often the annotator left a stretch unlabelled.
* Per trial (drawn from (seed, trial)): idle pauses between gestures (labelled ``Idle`` where the
  taxonomy has it, otherwise left unlabelled), unlabelled stretches ('' labels over ongoing motion),
  and the EmHT sensors' placement on the fingers (a small rotation and translation of each sensor in
  its pad frame; every ground-truth relation holds for the sensors as placed).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from midas_cli.errors import ConfigError
from midas_cli.geometry import matrices_from_angles

DIFFICULTIES = ("easy", "real")
DEFAULT_DIFFICULTY = "real"
_STYLE_STREAM, _TRIAL_STREAM, _PLACEMENT_STREAM = 19_001, 19_002, 19_003
MIN_MOTION_SEGMENT_S = 0.3
PLACEMENT_ROTATION_DEG = 6.0  # sd per axis
PLACEMENT_TRANSLATION_MM = 2.5  # sd per axis, in the pad frame


def check_difficulty(difficulty: str) -> str:
    if difficulty not in DIFFICULTIES:
        raise ConfigError(f"--difficulty {difficulty!r} unknown (expected {' or '.join(DIFFICULTIES)})")
    return difficulty


def subject_key(subject: str) -> int:
    """A stable integer of a subject id (crc32: the same in every process and Python version)."""
    return zlib.crc32(subject.encode("utf-8"))


@dataclass(frozen=True)
class SubjectStyle:
    """One simulated subject's way of moving (see module docstring)."""

    subject: str
    speed: float
    amplitude: float
    left_handed: bool
    bias_mm: np.ndarray  # (G, 2, 3) per gesture (taxonomy order) and hand: target offset bias
    bias_deg: np.ndarray  # (G, 2, 3) wrist angle bias
    consistency: float  # scales the per-trial spread of targets
    onset_lag_s: float  # mean shift of motion boundaries against label boundaries (+ = motion late)
    onset_jitter_s: float  # sd of that shift per boundary
    blend_s: float  # the move to the next gesture starts this long before its label
    tremor: float
    fine: float
    pause_probability: float  # per gesture boundary
    unlabelled_per_min: float

    def to_json(self) -> dict[str, Any]:
        return {"subject": self.subject, "speed": round(self.speed, 4), "amplitude": round(self.amplitude, 4),
                "left_handed": self.left_handed, "consistency": round(self.consistency, 4),
                "onset_lag_s": round(self.onset_lag_s, 4), "onset_jitter_s": round(self.onset_jitter_s, 4),
                "blend_s": round(self.blend_s, 4), "tremor_scale": round(self.tremor, 4),
                "fine_motion_scale": round(self.fine, 4), "pause_probability": round(self.pause_probability, 4),
                "unlabelled_per_min": round(self.unlabelled_per_min, 4),
                "gesture_bias_mm_rms": round(float(np.sqrt(np.mean(self.bias_mm ** 2))), 3)}


def subject_style(seed: int, subject: str, n_gestures: int) -> SubjectStyle:
    """The style of ``subject`` in the dataset of ``seed`` (independent of trial numbers)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, _STYLE_STREAM, subject_key(subject)]))
    return SubjectStyle(
        subject=subject,
        speed=float(np.exp(rng.normal(0.0, 0.25))),
        amplitude=float(np.exp(rng.normal(0.0, 0.2))),
        left_handed=bool(rng.random() < 0.25),
        bias_mm=rng.normal(0.0, 9.0, (n_gestures, 2, 3)),
        bias_deg=rng.normal(0.0, 8.0, (n_gestures, 2, 3)),
        consistency=float(rng.uniform(0.8, 2.0)),
        onset_lag_s=float(rng.uniform(-0.6, 0.8)),
        onset_jitter_s=float(rng.uniform(0.1, 0.6)),
        blend_s=float(rng.uniform(0.2, 1.2)),
        tremor=float(np.exp(rng.normal(0.0, 0.4))),
        fine=float(np.exp(rng.normal(0.0, 0.4))),
        pause_probability=float(rng.uniform(0.02, 0.12)),
        unlabelled_per_min=float(rng.uniform(0.0, 1.5)),
    )


def trial_rng(seed: int, trial: int) -> np.random.Generator:
    """The generator of a trial's difficulty draws (pauses, unlabelled stretches, motion boundaries)."""
    return np.random.default_rng(np.random.SeedSequence([seed, trial, _TRIAL_STREAM]))


def add_pauses(rng: np.random.Generator, style: SubjectStyle, drawn: list[tuple[str, float]], pause_label: str,
               pause_key: str) -> list[tuple[str, str, float]]:
    """(label, motion key, duration s): the subject's speed applied, idle pauses inserted between gestures."""
    out: list[tuple[str, str, float]] = []
    for i, (label, duration) in enumerate(drawn):
        out.append((label, label, max(duration / style.speed, 0.5)))
        if i < len(drawn) - 1 and rng.random() < style.pause_probability:
            out.append((pause_label, pause_key, float(rng.uniform(1.5, 6.0))))
    return out


def motion_bounds(rng: np.random.Generator, style: SubjectStyle, bounds: np.ndarray) -> np.ndarray:
    """Motion boundaries: label boundaries shifted by the subject's lag and jitter, kept increasing
    (each motion segment >= MIN_MOTION_SEGMENT_S); first and last equal the label bounds."""
    shifted = bounds.copy()
    shifted[1:-1] += style.onset_lag_s + rng.normal(0.0, style.onset_jitter_s, len(bounds) - 2)
    for i in range(1, len(shifted) - 1):
        shifted[i] = max(shifted[i], shifted[i - 1] + MIN_MOTION_SEGMENT_S)
    for i in range(len(shifted) - 2, 0, -1):
        shifted[i] = min(shifted[i], shifted[i + 1] - MIN_MOTION_SEGMENT_S)
    return shifted if np.all(np.diff(shifted) > 0.05) else bounds


def unlabelled_stretches(rng: np.random.Generator, style: SubjectStyle, total_s: float) -> np.ndarray:
    """(M, 2) s where the annotator left the frames unlabelled (the motion goes on)."""
    count = int(rng.poisson(style.unlabelled_per_min * total_s / 60.0))
    starts = np.sort(rng.uniform(0.0, max(total_s - 2.0, 0.1), count))
    return np.column_stack([starts, starts + rng.uniform(2.0, 8.0, count)])


@dataclass(frozen=True)
class Placement:
    """Where each of the 4 EmHT sensors sits on its finger pad in one session: rotation (4, 3, 3) and
    translation (4, 3) mm, both in the pad frame (a recorded sensor = pad @ (R, t))."""

    rotation: np.ndarray
    translation_mm: np.ndarray
    angles_deg: np.ndarray

    @classmethod
    def draw(cls, seed: int, trial: int) -> "Placement":
        rng = np.random.default_rng(np.random.SeedSequence([seed, trial, _PLACEMENT_STREAM]))
        angles = rng.normal(0.0, PLACEMENT_ROTATION_DEG, (4, 3))
        return cls(matrices_from_angles(angles), rng.normal(0.0, PLACEMENT_TRANSLATION_MM, (4, 3)), angles)

    def apply(self, positions: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Placed sensors from pad poses: positions (N, 4, 3) mm, rotations (N, 4, 3, 3)."""
        moved = positions + np.einsum("nsij,sj->nsi", rotations, self.translation_mm)
        return moved, np.einsum("nsij,sjk->nsik", rotations, self.rotation)

    def to_json(self) -> dict[str, Any]:
        return {"note": "per-session placement of each EmHT sensor on its finger pad, in the pad frame: "
                        "sensor = pad @ (R(angles), t); the ground-truth relations use the sensors as placed",
                "angles_deg": np.round(self.angles_deg, 4).tolist(),
                "translation_mm": np.round(self.translation_mm, 4).tolist()}
