"""Evaluation metrics as pure functions (DESIGN.md section 7; paper Appendix A.2.2, A.3).

Conventions: arrays are per-frame (N,); NaN marks a masked frame and is left out of every metric;
boolean states use True = pressed / closed (the positive class). A ratio whose denominator is 0
is NaN (undefined), never 0 or 1.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


def cosine_similarity(prediction: np.ndarray, truth: np.ndarray) -> float:
    """CoS of a whole one-axis trajectory about the ground truth's mean, over frames where both are valid:
    with c = mean(g), CoS = sum((p - c)(g - c)) / (|p - c| |g - c|). Without centring, any two
    trajectories far from the coordinate origin score ~1.000; about c, an offset or a wrong shape
    lowers it (the paper's EmHT-MTM values are ~0.8-0.95, not 1)."""
    p, g = _paired(prediction, truth)
    if len(g) == 0:
        return float("nan")
    centre = g.mean()
    p, g = p - centre, g - centre
    denom = np.linalg.norm(p) * np.linalg.norm(g)
    return float(p @ g / denom) if denom > 0 else float("nan")


def nrmse_percent(prediction: np.ndarray, truth: np.ndarray) -> float:
    """NRMSE(%) = 100 * RMSE / (max(truth) - min(truth)) over frames where both are valid."""
    p, g = _paired(prediction, truth)
    if len(g) == 0:
        return float("nan")
    span = g.max() - g.min()
    return float(100.0 * np.sqrt(np.mean((p - g) ** 2)) / span) if span > 0 else float("nan")


@dataclass(frozen=True)
class BinaryScores:
    """Frame-level confusion counts and the ratios derived from them (True = positive)."""

    tp: int
    fp: int
    fn: int
    tn: int
    precision: float
    recall: float
    f1: float
    accuracy: float
    iou: float

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


def binary_scores(prediction: np.ndarray, truth: np.ndarray) -> BinaryScores:
    """Confusion of two 0/1 (or bool) sequences over frames where both are valid (not NaN).

    precision = tp/(tp+fp), recall = tp/(tp+fn), F1 = 2tp/(2tp+fp+fn), accuracy = (tp+tn)/n,
    IoU = tp/(tp+fp+fn) (Jaccard of the positive frames).
    """
    p, g = _paired(prediction, truth)
    p, g = p > 0.5, g > 0.5
    tp, fp = int(np.sum(p & g)), int(np.sum(p & ~g))
    fn, tn = int(np.sum(~p & g)), int(np.sum(~p & ~g))
    return BinaryScores(tp, fp, fn, tn, _ratio(tp, tp + fp), _ratio(tp, tp + fn), _ratio(2 * tp, 2 * tp + fp + fn),
                        _ratio(tp + tn, tp + fp + fn + tn), _ratio(tp, tp + fp + fn))


def temporal_iou(prediction: np.ndarray, truth: np.ndarray, t_s: np.ndarray | None = None) -> float:
    """Temporal IoU of pressed intervals: duration(pred AND truth) / duration(pred OR truth).

    Each frame lasts until the next frame (``t_s`` (N,) seconds; uniform frames when None, the last
    frame gets the median frame duration). Frames where either input is NaN count for neither.
    """
    prediction, truth = np.asarray(prediction, float), np.asarray(truth, float)
    durations = _frame_durations(len(truth), t_s)
    ok = np.isfinite(prediction) & np.isfinite(truth)
    p, g = prediction[ok] > 0.5, truth[ok] > 0.5
    union = durations[ok][p | g].sum()
    return float(durations[ok][p & g].sum() / union) if union > 0 else float("nan")


def best_lag_frames(prediction: np.ndarray, truth: np.ndarray, max_shift: int) -> int:
    """The shift s in [-max_shift, max_shift] maximising the IoU of truth[t] and prediction[t + s]
    (positive s: the prediction is late). Ties go to the smallest |s|, then the negative one."""
    prediction, truth = np.asarray(prediction, float), np.asarray(truth, float)
    best_shift, best_iou = 0, -1.0
    for shift in sorted(range(-max_shift, max_shift + 1), key=lambda s: (abs(s), s)):
        if shift >= 0:
            iou = temporal_iou(prediction[shift:], truth[: len(truth) - shift])
        else:
            iou = temporal_iou(prediction[:shift], truth[-shift:])
        if np.isfinite(iou) and iou > best_iou + 1e-12:
            best_shift, best_iou = shift, iou
    return best_shift


def moving_average(values: np.ndarray, window: int) -> np.ndarray:
    """Centred moving average over ``window`` frames, ignoring NaN (NaN where the window has none)."""
    values = np.asarray(values, dtype=float)
    if window <= 1:
        return values.copy()
    ok = np.isfinite(values)
    kernel = np.ones(window)
    sums = np.convolve(np.where(ok, values, 0.0), kernel, mode="same")
    counts = np.convolve(ok.astype(float), kernel, mode="same")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / counts, np.nan)


def midpoint_threshold(values: np.ndarray, low_pct: float = 10.0, high_pct: float = 90.0) -> float:
    """A data-driven threshold between two states: the midpoint of the 10th and 90th percentiles."""
    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    if finite.size == 0:
        return float("nan")
    return float((np.percentile(finite, low_pct) + np.percentile(finite, high_pct)) / 2)


def closed_states(opening: np.ndarray, threshold: float | None = None, window: int = 1) -> tuple[np.ndarray, float]:
    """Grasper closed (1.0) / open (0.0) per frame from an opening signal (distance mm or angle deg):
    moving average over ``window`` frames, then closed where below ``threshold`` (default: the
    midpoint threshold of the smoothed signal). NaN where the signal is missing. Returns (states, threshold)."""
    smoothed = moving_average(opening, window)
    threshold = midpoint_threshold(smoothed) if threshold is None else threshold
    states = np.where(np.isfinite(smoothed), (smoothed < threshold).astype(float), np.nan)
    return states, float(threshold)


def _paired(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if a.shape != b.shape:
        raise ValueError(f"prediction {a.shape} and truth {b.shape} differ in shape")
    ok = np.isfinite(a) & np.isfinite(b)
    return a[ok], b[ok]


def _ratio(numerator: float, denominator: float) -> float:
    return float(numerator / denominator) if denominator > 0 else float("nan")


def _frame_durations(n: int, t_s: np.ndarray | None) -> np.ndarray:
    if t_s is None or n < 2:
        return np.ones(n)
    steps = np.diff(np.asarray(t_s, dtype=float))
    return np.append(steps, np.median(steps))
