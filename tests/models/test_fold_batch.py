"""Folds trained batched in one process (models/fold_batch.py, issue 27 item 5): with dropout 0 and the
same initial weights, K folds trained as one stacked computation end where K separate ``fit`` runs end
(padding, per-fold Adam state and step counts, selection); a fold with fewer sequences is not moved on
its idle steps; ``--fold all --fold-batch on`` writes the ordinary fold folders and cv.json."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from helpers.cli import midas
from helpers.gesture_sessions import write_louo_dataset
from midas_cli.commands.train import FOLD_BATCH_MODES
from midas_cli.errors import ConfigError
from midas_cli.models import fold_batch
from midas_cli.models.augment import input_shift
from midas_cli.models.sequences import Sequences
from midas_cli.models.train import TrainConfig, build_model, fit

DIMS, CLASSES = {"emht": 5}, 3
EMPTY = Sequences([], [], [])  # no validation units


def _sequences(seed: int, lengths: list[int]) -> Sequences:
    """Random inputs with labels that follow the first feature's sign (learnable, uneven lengths)."""
    rng = np.random.default_rng(seed)
    xs = [rng.normal(size=(t, DIMS["emht"])).astype(np.float32) for t in lengths]
    ys = [np.digitize(x[:, 0], [-0.4, 0.4]).astype(np.int64) for x in xs]
    ys[0][:3] = -1  # unlabelled frames are ignored alike
    return Sequences([(f"s{seed}-{i}", 0, t) for i, t in enumerate(lengths)], xs, ys)


def _model(name: str, options: dict) -> torch.nn.Module:
    torch.manual_seed(0)
    return build_model(name, DIMS, CLASSES, options)[0]


SMALL = {"mstcn": {"pg_layers": 3, "refinement_stages": 1, "refinement_layers": 3, "feature_maps": 8, "dropout": 0.0},
         "transformer": {"cnn_channels": 8, "d_model": 8, "n_heads": 2, "n_layers": 1, "ff_dim": 16, "window": 8,
                         "refinement_layers": 3, "refinement_maps": 8, "dropout": 0.0, "refinement_dropout": 0.0}}
# fold 2 has one sequence fewer than the others: idle on the last step of every epoch
FOLDS = [[40, 23, 31], [17, 44, 29], [35, 26]]


NAMES = ["emht.s1_x_mm", "emht.s1_y_mm", "d/dt emht.s1_x_mm", "sin emht.s1_roll_deg", "emht.s1_grasper_mm"]


def _shifts(trains: list[Sequences], augment: bool) -> list:
    """Each fold's position shift (``fit``'s augment), or None each."""
    return [input_shift(1.0, "pos", NAMES, t.x, seed=4) if augment else None for t in trains]


@pytest.mark.parametrize("name,batch_size,selection,decay,augment", [("mstcn", 1, "last", 0.0, False),
                                                                     ("transformer", 2, "best-val", 1e-3, False),
                                                                     ("mstcn", 1, "last", 0.0, True),
                                                                     ("mstcn", 1, "average", 0.0, True)])
def test_batched_folds_end_where_separate_runs_end(name, batch_size, selection, decay, augment):
    config = TrainConfig(model=name, epochs=3, batch_size=batch_size, lr=3e-3, selection=selection,
                         weight_decay=decay, seed=4)
    trains = [_sequences(k, lengths) for k, lengths in enumerate(FOLDS)]
    vals = [_sequences(10 + k, [30]) for k in range(len(FOLDS))]
    alone = [_model(name, SMALL[name]) for _ in FOLDS]
    histories = [fit(model, train, val, config, torch.device("cpu"), augment=shift)
                 for model, train, val, shift in zip(alone, trains, vals, _shifts(trains, augment))]
    together = [_model(name, SMALL[name]) for _ in FOLDS]
    stacked = fold_batch.fit_stacked(together, trains, vals, config, torch.device("cpu"), augments=_shifts(trains, augment))
    start = _model(name, SMALL[name]).state_dict()
    for k, (a, b) in enumerate(zip(alone, together)):
        for key, value in a.state_dict().items():
            assert not torch.equal(value, start[key]) or value.dim() == 0 or key == "positions"  # it trained
            mine = b.state_dict()[key]
            if key.endswith("in_proj_bias"):  # the key bias: its gradient is 0 up to rounding (softmax ignores a
                keep = torch.ones_like(value, dtype=torch.bool)  # constant added to every key), which Adam
                keep[len(value) // 3: 2 * len(value) // 3] = False  # scales up to lr-sized steps of noise
                mine, value = mine[keep], value[keep]
            torch.testing.assert_close(mine, value, rtol=1e-4, atol=2e-5, msg=f"fold {k} {key}")
        assert [h["epoch"] for h in stacked[k]] == [1, 2, 3]
        for mine, theirs in zip(stacked[k], histories[k]):
            assert mine["loss"] == pytest.approx(theirs["loss"], rel=1e-4)
            assert mine["val_accuracy"] == pytest.approx(theirs["val_accuracy"])


def test_an_idle_fold_keeps_its_weights_and_adam_state():
    """Fold 1 has one sequence, fold 0 three: over one epoch fold 1 takes exactly one Adam step, the same
    as training it alone for one epoch; a shared Adam (momentum moving it on the idle steps) fails this."""
    config = TrainConfig(model="mstcn", epochs=1, batch_size=1, lr=1e-2, selection="last", seed=0)
    short = _sequences(1, [30])
    alone = _model("mstcn", SMALL["mstcn"])
    fit(alone, short, EMPTY, config, torch.device("cpu"))
    models = [_model("mstcn", SMALL["mstcn"]) for _ in range(2)]
    fold_batch.fit_stacked(models, [_sequences(0, [30, 20, 25]), short], [EMPTY] * 2, config,
                           torch.device("cpu"))
    for key, value in alone.state_dict().items():
        torch.testing.assert_close(models[1].state_dict()[key], value, rtol=1e-5, atol=1e-6)


class _Operators(TorchDispatchMode):
    """Counts the aten operators (views apart: no kernel) dispatched while active, after vmap's batching."""

    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.count += not func.is_view
        return func(*args, **(kwargs or {}))


def _stacked_step_operators(name: str, k: int) -> int:
    """Operators of one training step of ``k`` folds batched (fit_stacked's ``StackedStep``: forward and
    loss under vmap, backward, the stacked Adam step), dropout on; the second step, after Adam's state exists."""
    options = {key: value for key, value in SMALL[name].items() if "dropout" not in key}
    step = fold_batch.StackedStep([_model(name, options) for _ in range(k)], torch.device("cpu"))
    x, y = torch.randn(k, 2, DIMS["emht"], 40), torch.randint(0, CLASSES, (k, 2, 40))
    mask, active = torch.ones(k, 2, 40, dtype=torch.bool), torch.ones(k, dtype=torch.bool)
    counter = _Operators()
    for counting in (False, True):
        with counter if counting else contextlib.nullcontext():
            step(x, y, mask, active, TrainConfig(lr=1e-3))
    return counter.count


@pytest.mark.parametrize("name", ["mstcn", "transformer"])
def test_a_batched_step_issues_as_many_operators_for_eight_folds_as_for_two(name):
    """The point of batching on a GPU: one stream of operators (kernels) whatever the number of folds. An
    operator vmap has no batching rule for runs once per fold and grows the count."""
    two, eight = _stacked_step_operators(name, 2), _stacked_step_operators(name, 8)
    assert two > 100 and eight == two


def test_mixed_precision_skips_the_step_of_a_fold_with_inf_gradients_and_halves_its_scale():
    """The CUDA path's per-fold GradScaler rule, checked on the CPU: fold 1's gradient overflowed."""
    weights = torch.ones(2, 3, requires_grad=True)
    state = fold_batch.new_state([weights], 2, torch.device("cpu"), mixed=True)
    weights.grad = torch.tensor([[1.0, -2.0, 3.0], [1.0, float("inf"), 0.0]]) * state.scale[:, None]
    fold_batch.adam_step([weights], state, torch.tensor([True, True]), TrainConfig(lr=0.1))
    assert state.steps.tolist() == [1.0, 0.0] and state.scale.tolist() == [2.0 ** 16, 2.0 ** 15]
    torch.testing.assert_close(weights[0].detach(), torch.tensor([0.9, 1.1, 0.9]))  # Adam's first step: lr x sign
    assert weights[1].tolist() == [1.0, 1.0, 1.0] and state.m[3:].tolist() == [0.0, 0.0, 0.0]


def test_the_mode_decides_from_the_device():
    assert fold_batch.enabled("auto", "cuda", 8) and not fold_batch.enabled("auto", "cpu", 8)
    assert fold_batch.enabled("on", "cpu", 2) and not fold_batch.enabled("on", "cuda", 1)
    assert not fold_batch.enabled("off", "cuda", 8)
    with pytest.raises(ConfigError, match="--fold-batch"):
        fold_batch.enabled("always", "cpu", 8)
    assert fold_batch.MODES == FOLD_BATCH_MODES  # the command checks the option without importing torch


def test_a_bad_fold_batch_mode_is_one_line_and_exit_2(jigsaws, tmp_path):
    result = midas("train", "gestures", str(jigsaws), "--split", "louo", "--fold", "all", "--fold-batch", "always",
                   "--out", str(tmp_path / "cv"))
    assert result.returncode == 2 and result.stderr.strip().count("\n") == 0 and "--fold-batch" in result.stderr
    assert not (tmp_path / "cv").exists()
    curve = midas("train", "gestures", str(jigsaws), "--model", "mstcn", "--split", "louo", "--fold", "all", "--fold-batch", "on",
                  "--curve-every", "5", "--out", str(tmp_path / "cv2"))  # batched folds are not scored per epoch
    assert curve.returncode == 2 and "--curve-every" in curve.stderr and curve.stderr.strip().count("\n") == 0


@pytest.fixture(scope="module")
def jigsaws(tmp_path_factory) -> Path:
    return write_louo_dataset(tmp_path_factory.mktemp("fb") / "data")


def test_fold_all_batched_writes_the_fold_folders_and_cv_json(jigsaws, tmp_path):
    out = tmp_path / "cv"
    result = midas("train", "gestures", str(jigsaws), "--model", "mstcn", "--modalities", "emht", "--features", "pos", "--split", "louo",
                   "--fold", "all", "--epochs", "2", "--fold-batch", "on", "--jobs", "2", "--out", str(out), "--json")
    assert result.returncode == 0, result.stderr
    assert "3 mstcn folds train batched in one process on cpu (--fold-batch on; --jobs 2 is not used" in result.stderr
    assert "3 baseline folds train batched" in result.stderr
    report = json.loads((out / "cv.json").read_text(encoding="utf-8"))
    assert [f["fold"] for f in report["folds"]] == [0, 1, 2] and report["baseline"]["n_folds"] == 3
    for root in (out, out / "baseline"):
        for k, user in enumerate("BCD"):
            run = json.loads((root / f"fold-{k}" / "run.json").read_text(encoding="utf-8"))
            assert run["split"]["group"] == user and run["train_config"]["fold"] == k
            assert len(run["history"]) == 2 and (root / f"fold-{k}" / "checkpoint.pt").is_file()
            tested = sorted(p.stem for p in (root / f"fold-{k}" / "predictions").iterdir())
            assert tested == sorted(u[0] for u in run["split"]["test"]) and len(tested) == 2
    again = midas("train", "gestures", str(jigsaws), "--model", "mstcn", "--modalities", "emht", "--features", "pos", "--split", "louo",
                  "--fold", "all", "--epochs", "2", "--fold-batch", "on", "--out", str(out), "--json")
    assert again.returncode == 0, again.stderr
    assert "train batched" not in again.stderr  # every fold finished: nothing is trained again
    assert json.loads(again.stdout)["pooled"] == json.loads(result.stdout)["pooled"]
