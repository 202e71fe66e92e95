"""The offline clean-up of predictions (--min-segment): short predicted segments merged into their longer
neighbour, the minimum taken from the training split's gesture lengths, raw metrics kept beside."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from helpers.cli import midas
from helpers.gesture_sessions import write_two_users
from midas_cli.errors import ConfigError, SessionError
from midas_cli.models import postprocess


def test_short_segments_go_to_their_longer_neighbour_shortest_first():
    pred = np.array([0, 0, 0, 1, 0, 0, 0, 2, 2, 2, 2, 3, 2])
    assert postprocess.merge_short_segments(pred, 2).tolist() == [0] * 7 + [2] * 6
    # shortest first, the leftmost of equals: [1 1] has only a right neighbour; then [2 2 2 2] is long enough
    assert postprocess.merge_short_segments(np.array([1, 1, 2, 2, 3, 3, 3, 3, 3]), 3).tolist() == [2] * 4 + [3] * 5
    # a 2-frame segment between a 3-frame and a 4-frame one joins the longer; a tie goes left
    assert postprocess.merge_short_segments(np.array([1, 1, 1, 2, 2, 3, 3, 3, 3]), 3).tolist() == [1] * 3 + [3] * 6
    assert postprocess.merge_short_segments(np.array([1, 1, 1, 2, 3, 3, 3]), 2).tolist() == [1] * 4 + [3] * 3
    assert postprocess.merge_short_segments(np.array([1, 1, 2, 2]), 3).tolist() == [2, 2, 2, 2]  # all short: one left
    assert postprocess.merge_short_segments(pred, 1).tolist() == pred.tolist()  # 1 frame: nothing to merge
    assert postprocess.merge_short_segments(np.array([4, 4]), 10).tolist() == [4, 4]  # one segment stays


def test_the_minimum_comes_from_the_training_labels_seconds_or_nothing():
    labels = [np.array([0] * 10 + [1] * 20 + [-1] * 3 + [2] * 40), np.array([1] * 30 + [0] * 50)]
    # gesture lengths 10, 20, 40, 30, 50 (unlabelled runs, -1, are no gesture): 2nd percentile 10.8 (the 5th: 12)
    assert postprocess.min_frames("auto", labels, 10.0) == 10
    assert postprocess.min_frames("1.5", labels, 10.0) == 15
    assert postprocess.min_frames("none", labels, 10.0) == 0
    for bad in ("-1", "0", "fast", "nan"):
        with pytest.raises(ConfigError, match="--min-segment"):
            postprocess.check(bad)


def _score(log_probs: np.ndarray, labels, log_trans=None) -> float:
    total = float(sum(log_probs[c, t] for t, c in enumerate(labels)))
    return total + (0.0 if log_trans is None else float(sum(log_trans[a, b] for a, b in zip(labels, labels[1:]) if a != b)))


def test_decode_finds_the_best_labelling_whose_segments_are_all_long_enough():
    rng = np.random.default_rng(3)
    for _ in range(150):  # against every labelling of small problems
        n_classes, length, minimum = int(rng.integers(2, 4)), int(rng.integers(2, 8)), int(rng.integers(1, 4))
        log_probs = np.log(rng.dirichlet(np.ones(n_classes), size=length).T)
        log_trans = np.log(rng.dirichlet(np.ones(n_classes), size=n_classes)) if rng.random() < 0.5 else None
        allowed = [y for y in itertools.product(range(n_classes), repeat=length)
                   if all(n >= minimum for _, n in postprocess._runs(np.array(y)))] if length >= minimum else \
            [(c,) * length for c in range(n_classes)]
        best = max(_score(log_probs, y, log_trans) for y in allowed)
        got = postprocess.decode(log_probs, minimum, log_trans)
        assert tuple(got) in allowed and _score(log_probs, got, log_trans) == pytest.approx(best)


def test_online_decoding_labels_each_frame_from_the_best_path_lag_frames_later():
    """Frame t's label is the one the best labelling of frames 0..t+lag gives it (every segment but the last
    at least the minimum long), against every labelling of small problems; the frames of the last ``lag``
    are decided at the end as ``decode`` decides them; a lag as long as the sequence is ``decode``."""
    rng = np.random.default_rng(11)
    for _ in range(120):
        n_classes, length, minimum = int(rng.integers(2, 4)), int(rng.integers(3, 8)), int(rng.integers(1, 4))
        lag = int(rng.integers(0, 4))
        log_probs = np.log(rng.dirichlet(np.ones(n_classes), size=length).T)
        log_trans = np.log(rng.dirichlet(np.ones(n_classes), size=n_classes)) if rng.random() < 0.5 else None
        if length < minimum:
            continue
        got = postprocess.decode_online(log_probs, minimum, log_trans, lag)
        final = postprocess.decode(log_probs, minimum, log_trans)
        for t in range(length - lag):
            seen = t + lag + 1  # frames 0..t+lag; every segment but the last at least the minimum long
            partial = [y for y in itertools.product(range(n_classes), repeat=seen)
                       if all(n >= minimum for _, n in postprocess._runs(np.array(y))[:-1])]
            best = max(partial, key=lambda y: _score(log_probs[:, :seen], y, log_trans))  # noqa: B023
            assert got[t] == best[t], (t, lag, minimum)
        assert list(got[max(0, length - lag):]) == list(final[max(0, length - lag):])
        assert list(postprocess.decode_online(log_probs, minimum, log_trans, length)) == list(final)


def test_the_online_decoder_steps_one_frame_at_a_time_as_decode_online_labels():
    rng = np.random.default_rng(5)
    log_probs = np.log(rng.dirichlet(np.ones(4) * 0.3, size=200).T)
    log_trans = postprocess.switch_scores([rng.integers(0, 4, 50)], 4, 5.0)
    decoder = postprocess.OnlineDecoder(4, 6, log_trans, lag=7)
    stepped = [decoder.step(log_probs[:, t]) for t in range(200)]
    assert all(out == [] for out in stepped[:7]) and all(len(out) == 1 for out in stepped[7:])
    labels = [x for out in stepped for x in out] + decoder.finish()
    assert labels == list(postprocess.decode_online(log_probs, 6, log_trans, 7))
    assert len(decoder.came_from) < 7 * 2 + 64  # only the last lag frames' back-pointers are needed
    with pytest.raises(ValueError, match="lag"):
        postprocess.OnlineDecoder(4, 6, None, lag=-1)


def test_decode_uses_the_probabilities_where_the_greedy_merge_uses_lengths():
    # a 2-frame blip of class 1 between a long 0 and a long 2: the merge gives it to the longer neighbour
    # (0); the frames themselves say 2 is nearly as likely as 1 and 0 unlikely.
    probs = np.full((3, 12), 0.01)
    probs[0, :6], probs[1, 6:8], probs[2, 6:8], probs[2, 8:] = 0.98, 0.55, 0.44, 0.98
    pred = probs.argmax(axis=0)
    assert postprocess.merge_short_segments(pred, 3).tolist() == [0] * 8 + [2] * 4
    assert postprocess.decode(np.log(probs), 3).tolist() == [0] * 6 + [2] * 6
    assert postprocess.decode(np.log(probs), 1).tolist() == pred.tolist()  # no minimum, no order: the argmax


def test_the_order_of_gestures_comes_from_training_and_can_forbid_a_change():
    train = [np.array([0, 0, 1, 1, -1, -1, 2, 2]), np.array([0, 1, 1, 2])]  # 0 -> 1 -> 2 (unlabelled skipped)
    counts = np.exp(postprocess.transition_log_probs(train, 3, smoothing=0.0))
    assert counts.tolist() == [[0, 1, 0], [0, 0, 1], [0.5, 0.5, 0]]  # 2 is never followed: uniform
    probs = np.full((3, 6), 0.1)
    probs[0, :3], probs[2, 3:] = 0.8, 0.8  # 0 then 2, which training never saw: 0 -> 1 -> 2 instead
    never = postprocess.transition_log_probs(train, 3, smoothing=0.0)
    assert postprocess.decode(np.log(probs), 1).tolist() == [0, 0, 0, 2, 2, 2]
    assert postprocess.decode(np.log(probs), 1, never).tolist() in ([0, 0, 0, 1, 2, 2], [0, 0, 1, 2, 2, 2])
    assert postprocess.decode(np.log(probs)[:, :0], 3).tolist() == []
    saved = postprocess.switch_scores(train, 3, 10.0)
    assert np.array_equal(postprocess.saved_switch_scores(saved.tolist(), 3), saved)
    assert postprocess.saved_switch_scores(None, 3) is None
    for bad in ([[0.0, 1.0]], [["a"] * 3] * 3, [[float("nan")] * 3] * 3, "scores", 5):  # a damaged run.json
        with pytest.raises(SessionError, match="switch_scores"):
            postprocess.saved_switch_scores(bad, 3)
    assert postprocess.decode(np.log(probs)[:, :2], 3).tolist() == [0, 0]  # shorter than the minimum: one class
    saved_min_segment, saved_decode_lag = postprocess.saved_min_segment, postprocess.saved_decode_lag
    assert (saved_min_segment({}), saved_decode_lag({})) == (0, None)  # a run from before either existed
    assert (saved_min_segment({"min_segment_frames": 12}), saved_decode_lag({"decode_lag_frames": 0})) == (12, 0)
    for bad in (-1, 2.5, True, "12", None):  # a damaged run.json: one clear error, never a decoder built on it
        with pytest.raises(SessionError, match="min_segment_frames"):
            saved_min_segment({"min_segment_frames": bad})
        if bad is not None:
            with pytest.raises(SessionError, match="decode_lag_frames"):
                saved_decode_lag({"decode_lag_frames": bad})


def test_the_grammar_weight_sets_what_a_change_of_gesture_costs():
    rng = np.random.default_rng(4)
    log_probs = [np.log(rng.dirichlet(np.ones(4), size=200).T)]  # noise: a change nearly every frame
    train = [np.array([0, 1, 2, 3, 0, 2, 1, 3])]
    counts = [len(postprocess._runs(postprocess.clean_up(log_probs, 0, postprocess.switch_scores(train, 4, w))[0]))
              for w in (0.1, 0.5, 2, 8, 1e4)]
    assert counts[0] > counts[1] > counts[2] > counts[3] > counts[4] == 1
    assert postprocess.switch_scores(train, 4, 0.0) is None  # weight 0: no decoding, the merge
    assert postprocess.clean_up(log_probs, 3, None)[0].tolist() == \
        postprocess.merge_short_segments(log_probs[0].argmax(axis=0), 3).tolist()
    assert postprocess.grammar_weight("auto", 10.0) == pytest.approx(10 * postprocess.WEIGHT_PER_HZ)
    assert postprocess.grammar_weight("2.5", 30.0) == 2.5
    assert postprocess.grammar_weight("none", 30.0) == 0
    for bad in ("-1", "cheap", "nan", "inf"):
        with pytest.raises(ConfigError, match="--grammar"):
            postprocess.check_weight(bad)
    assert postprocess.check_lag(0.0, causal=False) == 0.0 and postprocess.check_lag(1.5, causal=True) == 1.5
    for seconds, causal in ((-0.1, True), (float("nan"), True), (float("inf"), True), (1.0, False)):
        with pytest.raises(ConfigError, match="--decode-lag"):
            postprocess.check_lag(seconds, causal)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_two_users(tmp_path_factory.mktemp("postprocess") / "data", n_frames=150)


def _shortest_run(path: Path) -> int:
    pred = pd.read_csv(path, dtype=str)["prediction"].to_numpy()
    starts = np.r_[0, np.flatnonzero(pred[1:] != pred[:-1]) + 1]
    lengths = np.diff(np.r_[starts, len(pred)])
    return int(lengths.min()) if len(lengths) > 1 else len(pred)


def test_train_cleans_up_by_default_keeps_raw_and_re_evaluates_the_same(data, tmp_path):
    args = ("train", "gestures", str(data), "--model", "mstcn", "--modalities", "emht", "--features", "pos,vel", "--epochs", "1",
            "--split", "louo", "--fold", "0", "--json")
    run = midas(*args, "--out", str(tmp_path / "run"), check=True)
    test = json.loads((tmp_path / "run" / "metrics.json").read_text(encoding="utf-8"))["test"]
    minimum = test["min_segment_frames"]
    assert minimum > 1 and set(test["raw"]) == set(test["summary"])
    record = json.loads((tmp_path / "run" / "run.json").read_text(encoding="utf-8"))
    assert record["train_config"]["min_segment"] == "auto" and record["min_segment_frames"] == minimum
    rate = record["trials"][0]["rate_hz"]
    assert record["grammar_weight"] == pytest.approx(postprocess.WEIGHT_PER_HZ * rate) and test["grammar"]
    n_classes = len(record["classes"])
    assert np.asarray(record["switch_scores"]).shape == (n_classes, n_classes)
    for trial in (tmp_path / "run" / "predictions").glob("*.csv"):  # LOUO: each test trial is one sequence
        assert _shortest_run(trial) >= minimum
    again = midas("train", "gestures", str(data), "--eval-only", str(tmp_path / "run" / "checkpoint.pt"),
                  "--out", str(tmp_path / "eval"), "--json", check=True)
    assert json.loads(again.stdout)["test"] == json.loads(run.stdout)["test"]

    plain = midas(*args, "--min-segment", "none", "--grammar", "none", "--out", str(tmp_path / "plain"), check=True)
    assert "raw" not in json.loads((tmp_path / "plain" / "metrics.json").read_text(encoding="utf-8"))["test"]
    assert json.loads(plain.stdout)["test"]["accuracy"] == pytest.approx(test["raw"]["accuracy"])

    midas(*args, "--grammar", "none", "--out", str(tmp_path / "merged"), check=True)
    merged_test = json.loads((tmp_path / "merged" / "metrics.json").read_text(encoding="utf-8"))["test"]
    assert not merged_test["grammar"] and merged_test["raw"] == test["raw"]  # same network, other clean-up
    assert all(_shortest_run(t) >= minimum for t in (tmp_path / "merged" / "predictions").glob("*.csv"))

    bad = midas(*args, "--min-segment", "-2", "--out", str(tmp_path / "bad"))
    assert bad.returncode == 2 and "--min-segment" in bad.stderr and not (tmp_path / "bad" / "run.json").exists()
    bad = midas(*args, "--grammar", "lots", "--out", str(tmp_path / "bad"))
    assert bad.returncode == 2 and "--grammar" in bad.stderr and not (tmp_path / "bad" / "run.json").exists()
    bad = midas(*args, "--decode-lag", "1", "--out", str(tmp_path / "bad"))  # a lag is for a causal model
    assert bad.returncode == 2 and "--decode-lag is for --causal" in bad.stderr
    assert not (tmp_path / "bad" / "run.json").exists()
