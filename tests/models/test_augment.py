"""Position-shift augmentation (``--augment-shift``): what it shifts, and that it buys what it is for."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from helpers.cli import midas
from helpers.gesture_sessions import write_gesture_dataset
from midas_cli.errors import ConfigError
from midas_cli.models.augment import input_shift
from midas_cli.models.features import is_orientation, is_position
from midas_cli.models.sequences import Sequences
from midas_cli.models.train import TrainConfig, build_model, fit, predict

NAMES = ["psm.left_x_mm", "d/dt emht.s1_x_mm", "psm.left_vx_mm_s", "psm.left_R00", "emht.s2_z_mm",
         "handkp.right_thumb_y_mm", "psm.left_grasper_deg", "mtm.right_qw", "sin emht.s3_roll_deg",
         "psm.left_R12_w", "emht.s1_x_mm_R00x"]


def test_position_and_orientation_columns_are_told_apart():
    assert [is_position(n) for n in NAMES] == [True, False, False, False, True, True, False, False, False, False,
                                               False]
    assert [is_orientation(n) for n in NAMES] == [False, False, False, True, False, False, False, True, True, False,
                                                  False]


def test_orientation_shifts_move_orientation_columns_only_and_bad_sets_are_refused():
    x = [np.random.default_rng(0).normal(size=(20, len(NAMES))).astype(np.float32)]
    assert list(input_shift(1.0, "ori", NAMES, x, 0).columns) == [3, 7, 8]
    assert list(input_shift(1.0, "pos,ori", NAMES, x, 0).columns) == [0, 3, 4, 5, 7, 8]
    for bad in ("vel", "pos,pos", "", "pos;ori"):
        with pytest.raises(ConfigError, match="augment-features"):
            TrainConfig(augment_shift=1.0, augment_features=bad)


def test_each_sequence_gets_one_constant_per_position_column_and_new_draws_every_epoch():
    rng = np.random.default_rng(0)
    train = [rng.normal(size=(50, len(NAMES))).astype(np.float32) * 2.0 for _ in range(3)]
    before = [x.copy() for x in train]
    shift = input_shift(0.5, "pos", NAMES, train, seed=1)
    assert shift is not None and list(shift.columns) == [0, 4, 5]
    first, second = shift(train), shift(train)
    for x, old, a, b in zip(train, before, first, second):
        np.testing.assert_array_equal(x, old)  # the inputs are not touched
        moved = a - x
        assert np.allclose(moved, moved[0])  # constant over the sequence
        assert np.all(moved[0, [1, 2, 3, 6]] == 0) and np.all(moved[0, [0, 4, 5]] != 0)
        assert not np.allclose(a, b)  # redrawn each call (epoch)
    assert np.allclose(shift.scale, 0.5 * np.concatenate(train)[:, [0, 4, 5]].std(axis=0))
    # the spread of the draws is the asked one
    many = np.stack([(shift([train[0]])[0] - train[0])[0, [0, 4, 5]] for _ in range(4000)])
    np.testing.assert_allclose(many.std(axis=0), shift.scale, rtol=0.06)
    again = input_shift(0.5, "pos", NAMES, train, seed=1)
    np.testing.assert_array_equal(again(train)[0], first[0])  # seeded


def test_off_when_zero_or_without_positions():
    x = [np.ones((5, 2), dtype=np.float32)]
    assert input_shift(0.0, "pos", ["psm.left_x_mm", "psm.left_R00"], x, 0) is None
    assert input_shift(1.0, "pos", ["psm.left_vx_mm_s", "psm.left_R00"], x, 0) is None
    with pytest.raises(ConfigError, match="augment-shift"):
        TrainConfig(augment_shift=-0.1)


def _sequences(rng, n, offset=0.0):
    """Two classes in alternating blocks; in training the position separates them cleanly and the
    velocity noisily, so a model that is free to will lean on the position."""
    xs, ys = [], []
    for _ in range(n):
        y = (np.arange(200) // 25) % 2
        sign = 2.0 * y - 1.0
        pos = sign + 0.3 * rng.standard_normal(200) + offset
        vel = sign + 1.0 * rng.standard_normal(200)
        xs.append(np.column_stack([pos, vel]).astype(np.float32))
        ys.append(y.astype(np.int64))
    return Sequences([("t", 0, 200)] * n, xs, ys)


def _trained(train, augment):
    torch.manual_seed(0)
    model, _ = build_model("baseline", {"psm": 2}, 2, {})
    config = TrainConfig(model="baseline", epochs=40, batch_size=4, lr=1e-2, selection="last")
    fit(model, train, Sequences([], [], []), config, torch.device("cpu"), augment=augment)
    return model


def test_a_shifted_user_is_read_from_the_motion_not_from_where_it_happens():
    rng = np.random.default_rng(3)
    train, test = _sequences(rng, 16), _sequences(rng, 8, offset=2.5)  # the test "user" sits 2.5 sd off
    names = ["psm.left_x_mm", "psm.left_vx_mm_s"]

    def accuracy(model):
        return float(np.mean(np.concatenate(predict(model, test, torch.device("cpu"))) == np.concatenate(test.y)))

    plain = accuracy(_trained(train, None))
    shifted = accuracy(_trained(train, input_shift(3.0, "pos", names, train.x, seed=0)))
    assert plain < 0.65  # the position decides, and the offset user's is all one class
    assert shifted > 0.8 and shifted > plain + 0.2  # the velocity decides (0.88 measured; plain 0.53)


def test_cli_records_the_shift_and_refuses_a_negative_one(tmp_path):
    sessions = write_gesture_dataset(tmp_path / "data", n_trials=4, subjects=2, n_frames=120)
    args = ["train", "gestures", *map(str, sessions), "--model", "baseline", "--modalities", "emht",
            "--features", "pos,vel", "--epochs", "1", "--accelerator", "cpu"]
    result = midas(*args, "--augment-shift", "0.5", "--out", str(tmp_path / "run"))
    assert result.returncode == 0, result.stderr
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["train_config"]["augment_shift"] == 0.5
    bad = midas(*args, "--augment-shift", "-1", "--out", str(tmp_path / "bad"))
    assert bad.returncode == 2 and not (tmp_path / "bad").exists()
