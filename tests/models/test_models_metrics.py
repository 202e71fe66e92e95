"""Segmentation metrics against the reference definitions (MS-TCN eval.py), on hand-made sequences."""

from __future__ import annotations

import numpy as np
import pytest

from midas_cli.models import metrics as M


def reference_segments(y, bg=(-1,)):
    """Transcription of the reference get_labels_start_end_time (loop form)."""
    labels, starts, ends = [], [], []
    last = y[0]
    if y[0] not in bg:
        labels.append(y[0])
        starts.append(0)
    for i in range(len(y)):
        if y[i] != last:
            if y[i] not in bg:
                labels.append(y[i])
                starts.append(i)
            if last not in bg:
                ends.append(i)
            last = y[i]
    if last not in bg:
        ends.append(len(y))
    return labels, starts, ends


def reference_edit(p, y):
    P, Y = reference_segments(p)[0], reference_segments(y)[0]
    D = np.zeros((len(P) + 1, len(Y) + 1))
    D[:, 0] = np.arange(len(P) + 1)
    D[0, :] = np.arange(len(Y) + 1)
    for j in range(1, len(Y) + 1):
        for i in range(1, len(P) + 1):
            D[i, j] = D[i - 1, j - 1] if Y[j - 1] == P[i - 1] else min(D[i - 1, j], D[i, j - 1], D[i - 1, j - 1]) + 1
    return (1 - D[-1, -1] / max(len(P), len(Y))) * 100


def reference_f(p, y, overlap):
    pl, ps, pe = reference_segments(p)
    yl, ys, ye = reference_segments(y)
    tp = fp = 0
    hits = np.zeros(len(yl))
    for j in range(len(pl)):
        inter = np.minimum(pe[j], ye) - np.maximum(ps[j], ys)
        union = np.maximum(pe[j], ye) - np.minimum(ps[j], ys)
        iou = (1.0 * inter / union) * np.array([pl[j] == yl[x] for x in range(len(yl))])
        idx = iou.argmax()
        if iou[idx] >= overlap and not hits[idx]:
            tp += 1
            hits[idx] = 1
        else:
            fp += 1
    return tp, fp, len(yl) - hits.sum()


TRUTH = np.array([0] * 10 + [1] * 10 + [2] * 10)


def test_segments_runs_and_background():
    s = M.segments(np.array([-1, -1, 3, 3, 1, -1, 1, 1]))
    assert s.labels.tolist() == [3, 1, 1]
    assert s.starts.tolist() == [2, 4, 6]
    assert s.ends.tolist() == [4, 5, 8]


def test_perfect_prediction_scores_100():
    result = M.evaluate([TRUTH], [TRUTH], ["a", "b", "c"])["summary"]
    assert result["accuracy"] == 1.0 and result["edit"] == 100.0
    assert result["f1@10"] == result["f1@50"] == 100.0


def test_over_segmentation_lowers_edit_but_not_accuracy_much():
    pred = TRUTH.copy()
    pred[4] = 2  # two one-frame flickers inside the first segment
    pred[15] = 0
    summary = M.evaluate([pred], [TRUTH], ["a", "b", "c"])["summary"]
    assert summary["accuracy"] == pytest.approx(28 / 30)
    # P = a c a b a b c (7 segments) vs Y = a b c: 4 insertions -> 1 - 4/7
    assert summary["edit"] == pytest.approx((1 - 4 / 7) * 100)
    assert summary["edit"] == pytest.approx(reference_edit(pred, TRUTH))
    # P: a[0,4) c[4,5) a[5,10) b[10,15) a[15,16) b[16,20) c[20,30)
    # @10: a[0,4) IoU .4 TP, c FP, a[5,10) FP (already hit), b[10,15) TP, a FP, b[16,20) FP (hit), c TP
    assert M.overlap_counts(pred, TRUTH, 0.10) == (3, 4, 0)
    assert summary["f1@10"] == pytest.approx(200 * (3 / 7) * 1 / (3 / 7 + 1))
    # @60: only c[20,30) reaches the threshold (the a and b pieces have IoU .4 or .5)
    assert M.overlap_counts(pred, TRUTH, 0.60) == (1, 6, 2)


def test_shifted_boundary_keeps_edit_but_lowers_f1_at_high_overlap():
    pred = np.array([0] * 16 + [1] * 4 + [2] * 10)
    summary = M.evaluate([pred], [TRUTH], ["a", "b", "c"])["summary"]
    assert summary["edit"] == 100.0
    assert M.overlap_counts(pred, TRUTH, 0.25) == (3, 0, 0)
    assert M.overlap_counts(pred, TRUTH, 0.50) == (2, 1, 1)  # b: IoU 4/10


@pytest.mark.parametrize("seed", range(25))
def test_agrees_with_reference_on_random_sequences(seed):
    rng = np.random.default_rng(seed)
    truth = np.repeat(rng.integers(0, 4, 8), rng.integers(1, 9, 8))
    pred = truth.copy()
    flip = rng.random(len(pred)) < 0.2
    pred[flip] = rng.integers(-1, 4, flip.sum())
    assert M.edit_score(pred, truth) == pytest.approx(reference_edit(pred, truth))
    for k in M.OVERLAPS:
        assert M.overlap_counts(pred, truth, k) == tuple(int(v) for v in reference_f(pred, truth, k))


def test_f1_sums_counts_over_sequences_and_edit_averages():
    a = np.array([0, 0, 1, 1])
    b = np.array([1, 1, 1, 1])
    result = M.evaluate([a, a], [a, b], ["x", "y"])["summary"]
    assert result["edit"] == pytest.approx((100 + 50) / 2)
    # seq1: 2 TP; seq2: pred [0,2)->no match FP, pred [2,4) IoU .5 TP -> tp 3 fp 1 fn 0
    assert result["f1@50"] == pytest.approx(200 * 0.75 / 1.75)


def test_macro_precision_recall_and_confusion():
    truth = np.array([0, 0, 0, 1, 1, -1])
    pred = np.array([0, 1, 1, 1, 1, 0])
    out = M.evaluate([pred], [truth], ["x", "y"])
    assert out["confusion"] == [[1, 2], [0, 2]]
    assert out["summary"]["frames"] == 5
    assert out["summary"]["precision"] == pytest.approx((1.0 + 0.5) / 2)
    assert out["summary"]["recall"] == pytest.approx((1 / 3 + 1.0) / 2)
    per = {r["class"]: r for r in out["per_class"]}
    assert per["x"]["support"] == 3 and per["y"]["f1"] == pytest.approx(2 * 0.5 / 1.5)


def test_confusion_matrix_leaves_ignore_predictions_out_of_every_cell():
    # old code: truth 1 / prediction -1 landed in cell (0, 1); truth 0 / prediction -1 crashed bincount
    assert M.confusion_matrix(np.array([-1, 1]), np.array([1, 1]), 2).tolist() == [[0, 0], [0, 1]]
    assert M.confusion_matrix(np.array([-1, -1, 1, 0]), np.array([1, 0, 1, -1]), 2).tolist() == [[0, 0], [0, 1]]
    with pytest.raises(ValueError, match="prediction class indices"):
        M.confusion_matrix(np.array([2]), np.array([0]), 2)


def test_accuracy_leaves_out_unlabelled_truth_and_background_accuracy_counts_all_frames():
    truth = np.array([0, 0, 0, 1, 1, -1, -1, -1, 1])
    pred = np.array([0, -1, 1, 1, -1, -1, -1, 0, 1])
    out = M.evaluate([pred], [truth], ["x", "y"])
    summary = out["summary"]
    # labelled frames 0,1,2,3,4,8: right at 0, 3, 8 (the two -1 predictions are wrong)
    assert summary["accuracy"] == pytest.approx(3 / 6) and summary["frames"] == 6
    # all 9 frames, background a class: also right at 5 and 6 (predicted -1), wrong at 7
    assert summary["accuracy_with_background"] == pytest.approx(5 / 9) and summary["frames_all"] == 9
    assert out["confusion"] == [[1, 1], [0, 2]]
    per = {r["class"]: r for r in out["per_class"]}
    assert per["x"]["support"] == 3 and per["y"]["support"] == 3
    assert per["x"]["recall"] == pytest.approx(1 / 3) and per["y"]["recall"] == pytest.approx(2 / 3)
    assert per["x"]["precision"] == 1.0 and per["y"]["precision"] == pytest.approx(2 / 3)
    assert "left out" in out["definitions"]["accuracy"] and "background" in out["definitions"]["accuracy_with_background"]


@pytest.mark.parametrize("seed", range(10))
def test_background_accuracy_is_the_reference_all_frame_accuracy(seed):
    rng = np.random.default_rng(seed)
    truth = np.repeat(rng.integers(-1, 4, 8), rng.integers(1, 9, 8))
    pred = np.where(rng.random(len(truth)) < 0.3, rng.integers(-1, 4, len(truth)), truth)
    summary = M.evaluate([pred], [truth], list("abcd"))["summary"]
    reference = sum(int(g == r) for g, r in zip(truth, pred)) / len(truth)  # MS-TCN eval.py loop
    assert summary["accuracy_with_background"] == pytest.approx(reference)
    labelled = truth != -1
    if labelled.any():
        assert summary["accuracy"] == pytest.approx((pred[labelled] == truth[labelled]).mean())
