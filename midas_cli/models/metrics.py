"""Frame-wise and segmental metrics for action segmentation (pure numpy).

Segmental definitions follow the standard action-segmentation evaluation (Lea et al. 2017; the MS-TCN
repository's ``eval.py``):
  * a *segment* is a maximal run of one label; frames labelled ``ignore`` (default -1) are background:
    they end a segment and are never counted as one;
  * edit score = (1 - Levenshtein(segment labels of prediction, of ground truth) / max(len, len)) * 100,
    averaged over sequences;
  * F1@k: each predicted segment is matched to the ground-truth segment of the same label with the
    highest IoU; it is a true positive if IoU >= k/100 and that ground-truth segment was not already
    hit, else a false positive; unmatched ground-truth segments are false negatives. TP/FP/FN are
    summed over all sequences before computing precision, recall and F1 (x 100).
Frame metrics (accuracy, macro precision/recall/F1) are computed over all frames of all sequences
whose ground truth is not ``ignore`` (unlabelled frames are left out); a prediction of ``ignore`` on such
a frame is wrong: it falls in no cell of the confusion matrix but counts in its class's support.
Macro averages run over the classes present in the ground truth or the prediction.
``accuracy_with_background`` is the reference MS-TCN ``eval.py`` accuracy: over ALL frames, with
``ignore`` ("background") as one more class, right only where the prediction is ``ignore`` too.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

IGNORE = -1
OVERLAPS = (0.10, 0.25, 0.50)
DEFINITIONS = {
    "accuracy": "frames whose ground truth is labelled; unlabelled (background) frames are left out",
    "accuracy_with_background": "all frames, unlabelled = class 'background' (reference MS-TCN eval.py); "
                                "right only where the prediction is background too",
    "frames": "labelled ground-truth frames (accuracy, precision, recall, F1, confusion, support)",
    "frames_all": "all evaluated frames (accuracy_with_background)",
    "precision/recall/f1": "macro over classes in the ground truth or prediction, labelled frames only",
    "edit/f1@k": "segments of labelled frames; background ends a segment and is never one",
}


@dataclass(frozen=True)
class Segments:
    """Runs of one label: ``labels``, ``starts`` (inclusive) and ``ends`` (exclusive), frame indices."""

    labels: np.ndarray
    starts: np.ndarray
    ends: np.ndarray


def segments(frame_labels: np.ndarray, ignore: int = IGNORE) -> Segments:
    """Maximal runs of equal labels in ``frame_labels`` (T,), skipping runs of ``ignore``."""
    y = np.asarray(frame_labels)
    if y.size == 0:
        empty = np.zeros(0, dtype=np.int64)
        return Segments(empty, empty, empty)
    change = np.flatnonzero(y[1:] != y[:-1]) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [len(y)]])
    keep = y[starts] != ignore
    return Segments(y[starts][keep], starts[keep], ends[keep])


def levenshtein(a: Sequence[int], b: Sequence[int]) -> int:
    """Edit distance between two label sequences (insert, delete, substitute each cost 1)."""
    row = np.arange(len(b) + 1)
    for i, token in enumerate(a, start=1):
        previous, row = row, np.empty_like(row)
        row[0] = i
        for j in range(1, len(b) + 1):
            row[j] = min(previous[j] + 1, row[j - 1] + 1, previous[j - 1] + (token != b[j - 1]))
    return int(row[-1])


def edit_score(pred: np.ndarray, truth: np.ndarray, ignore: int = IGNORE) -> float:
    """Segmental edit score in [0, 100] of one sequence (100 = same ordered segment labels)."""
    p, y = segments(pred, ignore).labels, segments(truth, ignore).labels
    longest = max(len(p), len(y))
    if longest == 0:
        return 100.0
    return (1.0 - levenshtein(p.tolist(), y.tolist()) / longest) * 100.0


def overlap_counts(pred: np.ndarray, truth: np.ndarray, overlap: float, ignore: int = IGNORE) -> tuple[int, int, int]:
    """(TP, FP, FN) of predicted segments against ground-truth segments at IoU threshold ``overlap``."""
    p, y = segments(pred, ignore), segments(truth, ignore)
    hits = np.zeros(len(y.labels), dtype=bool)
    tp = fp = 0
    for label, start, end in zip(p.labels, p.starts, p.ends):
        intersection = np.minimum(end, y.ends) - np.maximum(start, y.starts)
        union = np.maximum(end, y.ends) - np.minimum(start, y.starts)
        iou = np.where(y.labels == label, intersection / union, 0.0) if len(y.labels) else np.zeros(0)
        best = int(np.argmax(iou)) if len(iou) else -1
        if best >= 0 and iou[best] >= overlap and not hits[best]:
            tp += 1
            hits[best] = True
        else:
            fp += 1
    return tp, fp, int(len(y.labels) - hits.sum())


def f1_from_counts(tp: int, fp: int, fn: int) -> float:
    """F1 in [0, 100] from summed counts (0 when there is nothing to match)."""
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    return float(200.0 * precision * recall / (precision + recall)) if precision + recall else 0.0


def confusion_matrix(pred: np.ndarray, truth: np.ndarray, n_classes: int, ignore: int = IGNORE) -> np.ndarray:
    """(n_classes, n_classes) int64 counts, rows = ground truth, columns = prediction, over the frames
    where neither is ``ignore`` (a frame predicted ``ignore`` is in no cell)."""
    pred, truth = np.asarray(pred).astype(np.int64), np.asarray(truth).astype(np.int64)
    keep = (truth != ignore) & (pred != ignore)
    for name, values in (("truth", truth[keep]), ("prediction", pred[keep])):
        if values.size and (values.min() < 0 or values.max() >= n_classes):
            raise ValueError(f"{name} class indices must be in [0, {n_classes}) or {ignore}, "
                             f"got {values.min()}..{values.max()}")
    index = truth[keep] * n_classes + pred[keep]
    return np.bincount(index, minlength=n_classes * n_classes).reshape(n_classes, n_classes)


def per_class_report(matrix: np.ndarray, class_names: Sequence[str], support: np.ndarray | None = None) -> list[dict]:
    """Per class: precision, recall, F1 (fractions) and support (ground-truth frames; default the
    matrix's row sums, pass the true counts when some frames were predicted ``ignore``)."""
    tp = np.diag(matrix).astype(float)
    predicted = matrix.sum(axis=0)
    actual = matrix.sum(axis=1) if support is None else np.asarray(support)
    precision = np.divide(tp, predicted, out=np.zeros_like(tp), where=predicted > 0)
    recall = np.divide(tp, actual, out=np.zeros_like(tp), where=actual > 0)
    denom = precision + recall
    f1 = np.divide(2 * precision * recall, denom, out=np.zeros_like(tp), where=denom > 0)
    return [{"class": name, "precision": float(precision[i]), "recall": float(recall[i]), "f1": float(f1[i]),
             "support": int(actual[i])} for i, name in enumerate(class_names)]


def evaluate(preds: Sequence[np.ndarray], truths: Sequence[np.ndarray], class_names: Sequence[str],
             ignore: int = IGNORE) -> dict:
    """All metrics over sequences (each (T_i,) int class indices). Fractions for frame metrics,
    0-100 for edit and F1@k (the convention of the segmentation literature)."""
    if len(preds) != len(truths) or not preds:
        raise ValueError(f"need equal, non-zero numbers of sequences, got {len(preds)} and {len(truths)}")
    pred_all, truth_all = np.concatenate(preds), np.concatenate(truths)
    n_classes = len(class_names)
    matrix = confusion_matrix(pred_all, truth_all, n_classes, ignore)
    labelled = truth_all != ignore
    support = np.bincount(truth_all[labelled].astype(np.int64), minlength=n_classes)
    report = per_class_report(matrix, class_names, support)
    present = (matrix.sum(axis=0) + support) > 0
    macro = {key: float(np.mean([r[key] for r, p in zip(report, present) if p])) for key in ("precision", "recall", "f1")}
    background_hits = int(((truth_all == ignore) & (pred_all == ignore)).sum())
    result = {"accuracy": float(np.trace(matrix) / max(int(labelled.sum()), 1)),
              "accuracy_with_background": float((np.trace(matrix) + background_hits) / max(len(truth_all), 1)),
              **macro, "edit": float(np.mean([edit_score(p, y, ignore) for p, y in zip(preds, truths)]))}
    for overlap in OVERLAPS:
        counts = np.sum([overlap_counts(p, y, overlap, ignore) for p, y in zip(preds, truths)], axis=0)
        result[f"f1@{int(overlap * 100)}"] = f1_from_counts(*(int(c) for c in counts))
    result["frames"] = int(labelled.sum())
    result["frames_all"] = int(len(truth_all))
    return {"summary": result, "per_class": report, "confusion": matrix.tolist(), "definitions": DEFINITIONS}
