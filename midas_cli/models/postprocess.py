"""Offline clean-up of frame predictions: no predicted segment shorter than real gestures, and gestures in
an order the task allows.

Frame-wise sequence models over-segment: a few frames of another class inside a gesture cost little
accuracy but break a segment in two, which the segmental scores (edit, F1@k) punish. ``--min-segment``
sets the shortest segment: ``auto`` takes it from the training split's own labels, the 2nd percentile of
the labelled gesture segments' lengths (in frames at the model rate), so no test data shape it and it
follows the dataset (JIGSAWS gestures at 10 Hz: 2 % are shorter than ~1.2 s); the 5th percentile (~1.5 s)
until the shifted-input models lost real short gestures to it. ``--grammar`` (``decode``, the default
since 2026-11-27) takes, of all labellings with no shorter segment, the one the frames' log-probabilities
make most likely, each change of gesture from a to b scoring W x log P(b after a) with P counted from the
training split's gesture order; ``--grammar none`` merges every short segment into its longer neighbour
instead (``merge_short_segments``). Both chosen on the JIGSAWS development tasks (README, "Defaults and
why"; BENCHMARKS.md, "The offline clean-up"). Both look at the whole sequence. A causal (live) model's
runs are decoded as a live decoder would decode them (``decode_online`` / ``OnlineDecoder``: the same
decoding run frame by frame, each frame labelled ``--decode-lag`` frames later from the best path so far;
with ``--grammar none``, the same with no gesture order): what `record --live-model` writes as the
``decoded`` class, measured by the run's metrics (raw: the network's own classes).
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from midas_cli.errors import ConfigError, SessionError

AUTO, NONE = "auto", "none"
PERCENTILE = 2.0
WEIGHT_PER_HZ = 1.0  # --grammar auto: the order's weight per Hz of the model rate (10 at 10 Hz)


def check(value: str) -> str:
    """``--min-segment`` ``value`` as given (auto, none, or seconds > 0 as text); ConfigError otherwise."""
    return _checked(value, "--min-segment", "seconds in (0, 3600)", lambda x: 0 < x < 3600)


def check_weight(value: str) -> str:
    """``--grammar`` ``value`` as given (auto, none, or a weight >= 0 as text); ConfigError otherwise."""
    return _checked(value, "--grammar", "a weight in [0, 1e6)", lambda x: 0 <= x < 1e6)


def _checked(value: str, option: str, expected: str, valid: Callable[[float], bool]) -> str:
    if value in (AUTO, NONE):
        return value
    try:
        number = float(value)
    except ValueError:
        number = float("nan")
    if not valid(number):
        raise ConfigError(f"{option} must be auto, none or {expected}, got {value!r}")
    return value


def check_lag(seconds: float, causal: bool) -> float:
    """``--decode-lag`` ``seconds`` as given; ConfigError for a negative one or one without ``causal``."""
    if not 0.0 <= seconds < 3600:
        raise ConfigError(f"--decode-lag must be seconds in [0, 3600), got {seconds!r}")
    if seconds and not causal:
        raise ConfigError("--decode-lag is for --causal models (a model that is not causal is decoded over the "
                          "whole sequence)")
    return seconds


def grammar_weight(setting: str, rate_hz: float) -> float:
    """The weight of the gesture order that ``setting`` gives (0: no order; the greedy merge offline)."""
    if setting == NONE:
        return 0.0
    return WEIGHT_PER_HZ * rate_hz if setting == AUTO else float(setting)


def clean_up(log_probs: Sequence[np.ndarray], minimum: int, switch: np.ndarray | None,
             lag: int | None = None) -> list[np.ndarray]:
    """Each sequence's (C, T) frame log-probabilities made a labelling: with ``switch`` (C, C), the score of
    each change of gesture, the best one whose segments are all ``minimum`` frames or longer (``decode``);
    without, the frames' most probable classes, short segments merged (``merge_short_segments``). ``lag``
    (frames; a causal model's runs): each frame decided that many frames later, as live (``decode_online``,
    no gesture order without ``switch``)."""
    if lag is not None:
        return [decode_online(lp, minimum, switch, lag) for lp in log_probs]
    if switch is None:
        return [merge_short_segments(lp.argmax(axis=0), minimum) for lp in log_probs]
    return [decode(lp, minimum, switch) for lp in log_probs]


def switch_scores(train_labels: Sequence[np.ndarray], n_classes: int, weight: float) -> np.ndarray | None:
    """``weight`` x log P(next gesture | gesture) from the training labels (``transition_log_probs``; the
    diagonal, never used, 0), or None for weight 0."""
    if weight <= 0:
        return None
    scores = weight * transition_log_probs(train_labels, n_classes)
    np.fill_diagonal(scores, 0.0)
    return scores


def saved_switch_scores(value: object, n_classes: int) -> np.ndarray | None:
    """A run's recorded ``switch_scores`` (None: the merge), checked: a (C, C) table of finite numbers."""
    if value is None:
        return None
    try:
        scores = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        scores = np.zeros(0)
    if scores.shape != (n_classes, n_classes) or not np.isfinite(scores).all():
        raise SessionError(f"the run's switch_scores are not a {n_classes} x {n_classes} table of numbers")
    return scores


def saved_decode_lag(saved: dict) -> int | None:
    """A saved run's ``decode_lag_frames`` (None: decoded over the whole sequence, as every run before it),
    checked: a whole number of frames >= 0."""
    lag = saved.get("decode_lag_frames")
    return None if lag is None else _whole_frames(lag, "decode_lag_frames")


def saved_min_segment(saved: dict) -> int:
    """A saved run's ``min_segment_frames`` (0 where it has none), checked: a whole number of frames >= 0."""
    return _whole_frames(saved.get("min_segment_frames", 0), "min_segment_frames")


def _whole_frames(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise SessionError(f"the run's {name} must be a whole number of frames >= 0, got {value!r}")
    return value


def min_frames(setting: str, train_labels: Sequence[np.ndarray], rate_hz: float) -> int:
    """The minimum segment length in frames that ``setting`` gives (0: no clean-up)."""
    if setting == NONE:
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


def transition_log_probs(train_labels: Sequence[np.ndarray], n_classes: int, smoothing: float = 1.0) -> np.ndarray:
    """(C, C) log P(next gesture | gesture) from the order of the labelled segments in ``train_labels``
    (unlabelled frames are skipped; a class never followed by another gets a uniform row), add-``smoothing``
    counts; the diagonal is -inf (a segment never follows itself)."""
    counts = np.zeros((n_classes, n_classes))
    for y in train_labels:
        order = [cls for cls, _ in _runs(y) if cls >= 0]
        for a, b in zip(order, order[1:]):
            if a != b:
                counts[a, b] += 1
    counts += smoothing
    np.fill_diagonal(counts, 0.0)
    unseen = counts.sum(axis=1) == 0
    counts[unseen] = 1.0
    counts[unseen, unseen.nonzero()[0]] = 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log(counts / counts.sum(axis=1, keepdims=True))


def decode(log_probs: np.ndarray, minimum: int, log_trans: np.ndarray | None = None) -> np.ndarray:
    """The labelling of the (C, T) frame ``log_probs`` with the highest total log probability (plus the
    ``log_trans`` score of each change of class, when given) among those whose segments are all at least
    ``minimum`` frames long: the exact version of ``merge_short_segments``, which decides from the
    segment lengths alone. Viterbi over (class, frames so far capped at ``minimum``). A sequence shorter
    than ``minimum`` gets its single most probable class."""
    return decode_online(log_probs, minimum, log_trans, lag=None)


def decode_online(log_probs: np.ndarray, minimum: int, log_trans: np.ndarray | None = None,
                  lag: int | None = 0) -> np.ndarray:
    """``decode`` as a live decoder with ``lag`` frames would label the sequence: frame t's label is
    decided at frame t + ``lag``, from the best labelling of the frames so far (its last segment may still
    be shorter than ``minimum``); the last ``lag`` frames are decided when the sequence ends, as ``decode``
    decides them. ``lag`` None (or >= T): ``decode`` itself. Each frame costs one Viterbi step and a
    walk back of ``lag`` frames (:class:`OnlineDecoder`)."""
    lp = np.asarray(log_probs, dtype=np.float64)
    n_classes, length = lp.shape
    d = max(1, int(minimum))
    if length == 0:
        return np.zeros(0, dtype=np.int64)
    if length < d:
        return np.full(length, int(lp.sum(axis=1).argmax()), dtype=np.int64)
    decoder = OnlineDecoder(n_classes, d, log_trans, length if lag is None else lag)
    out = [label for t in range(length) for label in decoder.step(lp[:, t])]
    return np.asarray(out + decoder.finish(), dtype=np.int64)


class OnlineDecoder:
    """``decode``'s Viterbi one frame at a time: ``step`` takes a frame's (C,) log-probabilities and
    returns the label of the frame ``lag`` frames before it (none for the first ``lag`` frames), read off
    the best path so far; ``finish`` returns the labels of the frames still undecided, from the best path
    whose last segment is complete (any path where none is). The states are (class, frames so far capped
    at ``minimum``); only the last ``lag`` frames' back-pointers are kept."""

    def __init__(self, n_classes: int, minimum: int, log_trans: np.ndarray | None, lag: int) -> None:
        if lag < 0:
            raise ValueError(f"lag must be >= 0 frames, got {lag}")
        self.d, self.lag, self.n_classes = max(1, int(minimum)), int(lag), n_classes
        switch = np.zeros((n_classes, n_classes)) if log_trans is None else np.asarray(log_trans, dtype=np.float64)
        self.switch = switch.copy()
        np.fill_diagonal(self.switch, -np.inf)
        self.score: np.ndarray | None = None
        self.came_from: list[np.ndarray] = []  # the class before a segment that starts at that frame
        self.stayed: list[np.ndarray] = []  # the capped state was reached from itself at that frame
        self.frames = 0

    def step(self, log_probs: np.ndarray) -> list[int]:
        lp = np.asarray(log_probs, dtype=np.float64)
        if self.score is None:
            self.score = np.full((self.n_classes, self.d), -np.inf)
            self.score[:, 0] = lp
            self.came_from.append(np.zeros(self.n_classes, dtype=np.int64))
            self.stayed.append(np.zeros(self.n_classes, dtype=bool))
        else:
            score, d, n = self.score, self.d, self.n_classes
            new = np.full_like(score, -np.inf)
            candidates = score[:, d - 1][:, None] + self.switch  # (from, to)
            best = candidates.argmax(axis=0)
            entering = candidates[best, np.arange(n)]
            if d == 1:
                stayed = score[:, 0] >= entering
                new[:, 0] = np.where(stayed, score[:, 0], entering)
            else:
                new[:, 1:] = score[:, :-1]
                stayed = score[:, d - 1] > new[:, d - 1]
                new[:, d - 1] = np.maximum(new[:, d - 1], score[:, d - 1])
                new[:, 0] = entering
            self.came_from.append(best)
            self.stayed.append(stayed)
            self.score = new + lp[:, None]
        self.frames += 1
        keep = max(1, self.lag)
        if len(self.came_from) >= 2 * keep + 64:  # trimmed now and then: a list's front is dear to delete
            del self.came_from[:-keep], self.stayed[:-keep]
        if self.frames <= self.lag:
            return []
        cls, k = np.unravel_index(int(self.score.argmax()), self.score.shape)
        return [self._path(int(cls), int(k), self.lag)[0]]

    def finish(self) -> list[int]:
        """The labels of the last ``min(lag, frames)`` frames, oldest first."""
        if self.score is None:
            return []
        complete = self.score[:, self.d - 1]
        if np.isfinite(complete).any():
            cls, k = int(complete.argmax()), self.d - 1
        else:
            cls, k = (int(i) for i in np.unravel_index(int(self.score.argmax()), self.score.shape))
        return self._path(cls, k, min(self.lag, self.frames) - 1) if self.lag else []

    def _path(self, cls: int, k: int, back: int) -> list[int]:
        """The labels of the ``back`` + 1 last frames on the path that ends in state (``cls``, ``k``)."""
        out = [cls]
        for i in range(back):  # from the newest kept frame back
            came, stayed = self.came_from[-1 - i], self.stayed[-1 - i]
            if not (k == self.d - 1 and stayed[cls]):
                cls, k = (int(came[cls]), self.d - 1) if k == 0 else (cls, k - 1)
            out.append(cls)
        return out[::-1]
