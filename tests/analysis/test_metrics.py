"""Metric functions against hand-computed examples (a wrong formula fails these)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from midas_cli.analysis.metrics import (best_lag_frames, binary_scores, closed_states, cosine_similarity,
                                        midpoint_threshold, moving_average, nrmse_percent, temporal_iou)

NAN = float("nan")


def test_cosine_similarity_hand_computed_and_ignores_masked_frames() -> None:
    # p = (1, 2, 2), g = (2, 0, 1), about mean(g) = 1: (0, 1, 1) . (1, -1, 0) = -1, norms sqrt2 sqrt2 -> -0.5
    assert cosine_similarity(np.array([1, 2, 2, NAN]), np.array([2, 0, 1, 7])) == pytest.approx(-0.5)
    g = np.array([100.0, 101.0, 102.0])  # far from the origin: raw cosine would be ~1 for anything nearby
    assert cosine_similarity(g, g) == pytest.approx(1.0)
    assert cosine_similarity(g[::-1].copy(), g) == pytest.approx(-1.0)
    # not a Pearson correlation: an offset lowers it (about mean(g): (9, 10, 11) . (-1, 0, 1) = 2)
    assert cosine_similarity(g + 10, g) == pytest.approx(2 / (math.sqrt(302) * math.sqrt(2)))


def test_nrmse_is_rmse_over_ground_truth_range_in_percent() -> None:
    truth = np.array([0.0, 10.0, 5.0, 5.0])
    pred = np.array([1.0, 9.0, 5.0, 7.0])  # errors 1, -1, 0, 2 -> RMSE sqrt(6/4); range 10
    assert nrmse_percent(pred, truth) == pytest.approx(100 * math.sqrt(1.5) / 10)
    assert math.isnan(nrmse_percent(np.ones(3), np.ones(3)))  # zero range: undefined, not 0


def test_binary_scores_hand_computed() -> None:
    pred = np.array([1, 1, 0, 0, 1, 0, NAN])
    truth = np.array([1, 0, 1, 0, 1, 0, 1])  # tp 2, fp 1, fn 1, tn 2 (last frame masked)
    s = binary_scores(pred, truth)
    assert (s.tp, s.fp, s.fn, s.tn) == (2, 1, 1, 2)
    assert s.precision == pytest.approx(2 / 3)
    assert s.recall == pytest.approx(2 / 3)
    assert s.f1 == pytest.approx(4 / 6)
    assert s.accuracy == pytest.approx(4 / 6)
    assert s.iou == pytest.approx(2 / 4)


def test_binary_scores_undefined_ratios_are_nan() -> None:
    s = binary_scores(np.zeros(4), np.zeros(4))
    assert math.isnan(s.precision) and math.isnan(s.recall) and math.isnan(s.f1) and math.isnan(s.iou)
    assert s.accuracy == 1.0


def test_temporal_iou_weights_frames_by_duration() -> None:
    pred = np.array([1, 1, 0, 0])
    truth = np.array([0, 1, 1, 0])
    assert temporal_iou(pred, truth) == pytest.approx(1 / 3)
    # frame 1 lasts 3 s, frames 0 and 2 last 1 s: intersection 3, union 1 + 3 + 1
    assert temporal_iou(pred, truth, np.array([0.0, 1.0, 4.0, 5.0])) == pytest.approx(3 / 5)


def test_best_lag_finds_a_late_detection() -> None:
    truth = np.zeros(100)
    truth[20:40] = 1
    truth[60:70] = 1
    late = np.roll(truth, 5)  # detection 5 frames late
    assert best_lag_frames(late, truth, 10) == 5
    assert best_lag_frames(np.roll(truth, -3), truth, 10) == -3


def test_moving_average_ignores_nan_and_centres() -> None:
    smoothed = moving_average(np.array([0.0, 3.0, NAN, 9.0, 0.0]), 3)
    assert smoothed.tolist() == pytest.approx([1.5, 1.5, 6.0, 4.5, 4.5])


def test_closed_states_below_the_midpoint_threshold() -> None:
    opening = np.array([10.0] * 10 + [50.0] * 10)  # closed grip = small opening
    assert midpoint_threshold(opening) == pytest.approx(30.0)
    states, threshold = closed_states(opening)
    assert threshold == pytest.approx(30.0)
    assert states.tolist() == [1.0] * 10 + [0.0] * 10
