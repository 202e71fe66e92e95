"""How well extracted pedal states match known ones (the generator's schedule): frame-level F1 and
onset errors, per pedal. Both inputs are 0/1 arrays indexed by the same 0-based frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PedalAgreement:
    """``f1`` over frames (1.0 when neither side is ever pressed); ``onset_errors`` (frames) of every
    true press onset to the nearest detected onset (None when nothing was detected)."""

    pedal: str
    f1: float
    true_onsets: int
    detected_onsets: int
    onset_errors: tuple[int | None, ...]

    @property
    def max_onset_error(self) -> int | None:
        """Largest onset error in frames; None when a true onset has no detected onset at all."""
        if any(e is None for e in self.onset_errors):
            return None
        return max((int(e) for e in self.onset_errors), default=0)


def onsets(states: np.ndarray) -> np.ndarray:
    """Frames where a 0/1 series switches to 1 (a series starting pressed has an onset at 0)."""
    series = np.asarray(states, dtype=np.int8)
    return np.flatnonzero(np.diff(series, prepend=0) == 1)


def frame_f1(detected: np.ndarray, truth: np.ndarray) -> float:
    detected, truth = np.asarray(detected, bool), np.asarray(truth, bool)
    total = int(detected.sum() + truth.sum())
    return 1.0 if total == 0 else 2.0 * int((detected & truth).sum()) / total


def compare(pedal: str, detected: np.ndarray, truth: np.ndarray) -> PedalAgreement:
    """Agreement of two equally long 0/1 series of one pedal."""
    if len(detected) != len(truth):
        raise ValueError(f"{pedal}: {len(detected)} detected frames vs {len(truth)} true frames")
    found, wanted = onsets(detected), onsets(truth)
    errors = tuple(int(np.abs(found - t).min()) if len(found) else None for t in wanted)
    return PedalAgreement(pedal, frame_f1(detected, truth), len(wanted), len(found), errors)
