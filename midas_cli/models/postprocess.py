"""Offline clean-up of frame predictions: predicted segments shorter than real gestures are merged away.

Frame-wise sequence models over-segment: a few frames of another class inside a gesture cost little
accuracy but break a segment in two, which the segmental scores (edit, F1@k) punish. ``--min-segment``
merges every predicted segment shorter than a minimum length into its longer neighbour, shortest first,
until none is left. ``auto`` takes the minimum from the training split's own labels: the 2nd percentile
of the labelled gesture segments' lengths (in frames at the model rate), so no test data shape it and
it follows the dataset (JIGSAWS gestures at 10 Hz: 2 % are shorter than ~1.2 s). Chosen on the JIGSAWS
development tasks (README, "Defaults and why"): the 5th percentile (~1.5 s) until the shifted-input
models, whose predictions break up less, lost real short gestures to it (BENCHMARKS.md). It looks at
the whole sequence, so a causal (live) model's runs keep their raw predictions (``auto`` means ``none``
there).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from midas_cli.errors import ConfigError

AUTO, NONE = "auto", "none"
PERCENTILE = 2.0


def check(value: str) -> str:
    """``value`` as given (auto, none, or seconds > 0 as text); ConfigError otherwise."""
    if value in (AUTO, NONE):
        return value
    try:
        seconds = float(value)
    except ValueError:
        seconds = -1.0
    if not 0 < seconds < 3600:
        raise ConfigError(f"--min-segment must be auto, none or seconds in (0, 3600), got {value!r}")
    return value


def min_frames(setting: str, train_labels: Sequence[np.ndarray], rate_hz: float, causal: bool) -> int:
    """The minimum segment length in frames that ``setting`` gives (0: no clean-up)."""
    if setting == NONE or (setting == AUTO and causal):
        return 0
    if setting != AUTO:
        return max(0, int(round(float(setting) * rate_hz)))
    lengths = [length for y in train_labels for cls, length in _runs(y) if cls >= 0]
    return int(np.floor(np.percentile(lengths, PERCENTILE))) if lengths else 0


def merge_short_segments(pred: np.ndarray, minimum: int) -> np.ndarray:
    """``pred`` with every segment shorter than ``minimum`` frames given its longer neighbour's class
    (the left one on a tie), shortest segment first, until every segment is at least ``minimum`` long or
    one segment is left."""
    out = np.asarray(pred).copy()
    if minimum <= 1:
        return out
    while True:
        starts = np.r_[0, np.flatnonzero(np.diff(out)) + 1]
        lengths = np.diff(np.r_[starts, len(out)])
        i = int(np.argmin(lengths)) if len(lengths) > 1 else 0
        if len(lengths) <= 1 or lengths[i] >= minimum:
            return out
        left = lengths[i - 1] if i > 0 else -1
        right = lengths[i + 1] if i + 1 < len(lengths) else -1
        out[starts[i]:starts[i] + lengths[i]] = out[starts[i - 1]] if left >= right else out[starts[i + 1]]


def _runs(y: np.ndarray) -> list[tuple[int, int]]:
    """(class, length) of each run of equal values in ``y``."""
    y = np.asarray(y)
    if not len(y):
        return []
    starts = np.r_[0, np.flatnonzero(np.diff(y)) + 1]
    return list(zip(y[starts].tolist(), np.diff(np.r_[starts, len(y)]).tolist()))
