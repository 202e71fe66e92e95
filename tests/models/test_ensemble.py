"""Ensembles (models/ensemble.py, issue 27): each member trains exactly as a run of its own would (its
recipe, its seed, the run's shift), one progress count over all; the ensemble predicts the log of its
members' mean probabilities; batched folds train each member stacked in turn and end where separate fits
end; from the CLI a run records its members and reloads from its checkpoint; learning curves are refused."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers.cli import midas
from helpers.gesture_sessions import write_louo_dataset
from midas_cli.errors import ConfigError
from midas_cli.models import cv, fold_batch
from midas_cli.models.augment import input_shift
from midas_cli.models.sequences import Sequences
from midas_cli.models.ensemble import member_configs
from midas_cli.models.train import TrainConfig, build_model, fit

DIMS, CLASSES = {"emht": 5}, 3
EMPTY = Sequences([], [], [])
NAMES = ["emht.s1_x_mm", "emht.s1_y_mm", "d/dt emht.s1_x_mm", "sin emht.s1_roll_deg", "emht.s1_grasper_mm"]
SMALL = {"mstcn": {"pg_layers": 3, "refinement_stages": 1, "refinement_layers": 3, "feature_maps": 8},
         "transformer": {"cnn_channels": 8, "d_model": 8, "n_heads": 2, "n_layers": 1, "ff_dim": 16, "window": 8,
                         "refinement_layers": 3, "refinement_maps": 8}}
QUIET = {name: {**options, **({"dropout": 0.0, "refinement_dropout": 0.0} if name == "transformer" else
                              {"dropout": 0.0})} for name, options in SMALL.items()}
CPU = torch.device("cpu")


def _sequences(seed: int, lengths: list[int]) -> Sequences:
    """Random inputs with labels that follow the first feature's sign (learnable, uneven lengths)."""
    rng = np.random.default_rng(seed)
    xs = [rng.normal(size=(t, DIMS["emht"])).astype(np.float32) for t in lengths]
    ys = [np.digitize(x[:, 0], [-0.4, 0.4]).astype(np.int64) for x in xs]
    return Sequences([(f"s{seed}-{i}", 0, t) for i, t in enumerate(lengths)], xs, ys)


def _ensemble(options: dict = SMALL) -> torch.nn.Module:
    torch.manual_seed(0)
    return build_model("ensemble", DIMS, CLASSES, {"members": ["mstcn", "transformer"], "member_options": options})[0]


def test_members_train_with_their_own_recipe_and_seed_as_runs_of_their_own():
    ensemble = _ensemble()
    alone = copy.deepcopy(list(ensemble.members))  # the same initial weights
    train = _sequences(0, [40, 23, 31, 27, 35])
    ticks: list[tuple[int, int]] = []
    torch.manual_seed(11)  # dropout draws from torch's generator: the members use it one after another
    history = fit(ensemble, train, EMPTY, TrainConfig(model="ensemble", epochs=2, seed=3), CPU,
                  lambda epoch, total, _: ticks.append((epoch, total)),
                  augment=input_shift(1.0, "pos", NAMES, train.x, seed=4))
    torch.manual_seed(11)
    shift = input_shift(1.0, "pos", NAMES, train.x, seed=4)  # the run's one shift stream, shared in turn
    for i, (name, member) in enumerate(zip(("mstcn", "transformer"), alone)):
        fit(member, train, EMPTY, TrainConfig(model=name, epochs=2, seed=3 + i), CPU, augment=shift)
        for key, value in member.state_dict().items():
            assert torch.equal(ensemble.members[i].state_dict()[key], value), f"member {i} {key}"
    assert [(h["member"], h["model"], h["epoch"]) for h in history] == [
        (0, "mstcn", 1), (0, "mstcn", 2), (1, "transformer", 1), (1, "transformer", 2)]
    assert ticks == [(1, 4), (2, 4), (3, 4), (4, 4)]  # one count over every member's epochs


def test_member_configs_take_each_members_recipe_unless_the_run_sets_a_field():
    members = ("mstcn", "transformer", "mstcn")
    recipe = member_configs(TrainConfig(model="ensemble", seed=5).resolved(), members)
    assert [(c.model, c.epochs, c.batch_size, c.lr, c.selection, c.seed) for c in recipe] == [  # the ensemble's weights
        ("mstcn", 20, 1, 5e-4, "average", 5), ("transformer", 10, 4, 1e-3, "average", 6), ("mstcn", 20, 1, 5e-4, "average", 7)]
    alone = member_configs(TrainConfig(model="ensemble", selection="last").resolved(), members)
    assert {c.selection for c in alone} == {"last"}
    assert TrainConfig(model="mstcn").resolved().selection == "last"  # a network alone keeps its own recipe
    assert {(c.augment_shift, c.augment_features) for c in recipe} == {(1.0, "pos,ori")}  # the ensemble's
    given = member_configs(TrainConfig(model="ensemble", epochs=3, lr=1e-2, augment_shift=0.0).resolved(), members)
    assert {(c.epochs, c.lr, c.augment_shift) for c in given} == {(3, 1e-2, 0.0)}


def test_the_ensemble_predicts_the_log_of_its_members_mean_probabilities():
    ensemble = _ensemble().eval()
    x, mask = torch.randn(2, 5, 30), torch.ones(2, 30, dtype=torch.bool)
    with torch.no_grad():
        out = ensemble.frame_logits(ensemble(x, mask))
        probs = [torch.softmax(m.frame_logits(m(x, mask)), dim=1) for m in ensemble.members]
    torch.testing.assert_close(out, torch.log(torch.stack(probs).mean(dim=0)))
    assert out.shape == (2, CLASSES, 30)
    with pytest.raises(TypeError, match="member by member"):
        ensemble.loss(out, torch.zeros(2, 30, dtype=torch.long), mask)


@pytest.mark.parametrize("options,match", [({"members": ["mstcn", "ensemble"]}, "not a single model"),
                                           ({"members": ["lstm"]}, "'lstm' is not a single model"),
                                           ({"members": []}, "at least one member"),
                                           ({"member_options": {"lstm": {}}}, "not a member"),
                                           ({"member_options": {"mstcn": {"layers": 2}}}, "layers")])
def test_a_bad_ensemble_is_refused(options, match):
    with pytest.raises(ConfigError, match=match):
        build_model("ensemble", DIMS, CLASSES, options)


def test_batched_folds_of_an_ensemble_end_where_separate_fits_end():
    config = TrainConfig(model="ensemble", epochs=2, seed=4)
    trains = [_sequences(k, lengths) for k, lengths in enumerate([[40, 23, 31], [17, 44, 29, 33]])]
    alone = [_ensemble(QUIET) for _ in trains]
    separate = [fit(model, train, EMPTY, config, CPU) for model, train in zip(alone, trains)]
    together = [_ensemble(QUIET) for _ in trains]
    stacked = fold_batch.fit_stacked(together, trains, [EMPTY, EMPTY], config, CPU)
    for k, (a, b) in enumerate(zip(alone, together)):
        for key, value in a.state_dict().items():
            mine = b.state_dict()[key]
            if key.endswith("in_proj_bias"):  # the attention key bias: gradient 0 up to rounding (see test_fold_batch)
                keep = torch.ones_like(value, dtype=torch.bool)
                keep[len(value) // 3: 2 * len(value) // 3] = False
                mine, value = mine[keep], value[keep]
            torch.testing.assert_close(mine, value, rtol=1e-4, atol=2e-5, msg=f"fold {k} {key}")
        assert [(h["member"], h["epoch"]) for h in stacked[k]] == [(h["member"], h["epoch"]) for h in separate[k]]
        assert [h["loss"] for h in stacked[k]] == pytest.approx([h["loss"] for h in separate[k]], rel=1e-4)


@pytest.fixture(scope="module")
def jigsaws(tmp_path_factory) -> Path:
    return write_louo_dataset(tmp_path_factory.mktemp("ens") / "data")


def test_cli_ensemble_run_records_its_members_and_reloads_from_its_checkpoint(jigsaws, tmp_path):
    common = ("--modalities", "emht", "--features", "pos", "--split", "louo")
    run = midas("train", "gestures", str(jigsaws), *common, "--fold", "1", "--model", "ensemble", "--epochs", "1",
                "--out", str(tmp_path / "run"), "--json")
    assert run.returncode == 0, run.stderr
    record = json.loads((tmp_path / "run" / "run.json").read_text(encoding="utf-8"))
    assert record["model_config"]["members"] == ["mstcn", "transformer", "mstcn"]
    assert [(m["model"], m["seed"], m["epochs"]) for m in record["recipe"]["members"]] == [
        ("mstcn", 0, 1), ("transformer", 1, 1), ("mstcn", 2, 1)]
    assert [h["member"] for h in record["history"]] == [0, 1, 2]
    assert cv._epochs(record) == 1  # what cv.md says it trained: --epochs, every member's
    assert cv._epochs({"train_config": {"epochs": None}, "recipe": {"members": [{"epochs": 20}, {"epochs": 10}]}}) \
        == "20+10"  # left to the members' recipes
    again = midas("train", "gestures", str(jigsaws), "--eval-only", str(tmp_path / "run" / "checkpoint.pt"),
                  "--out", str(tmp_path / "eval"), "--json")
    assert again.returncode == 0, again.stderr
    assert json.loads(again.stdout)["test"] == json.loads(run.stdout)["test"]
    # a checkpoint of another composition (an earlier default's) rebuilds the members it recorded, not today's
    saved = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    saved["model_config"]["members"] = ["mstcn", "transformer"]
    saved["state_dict"] = {k: v for k, v in saved["state_dict"].items() if not k.startswith("members.2.")}
    torch.save(saved, tmp_path / "two.pt")
    two = midas("train", "gestures", str(jigsaws), "--eval-only", str(tmp_path / "two.pt"), "--out",
                str(tmp_path / "eval-two"), "--json")
    assert two.returncode == 0, two.stderr  # a strict load: three members built would not take two's weights
    curve = midas("train", "gestures", str(jigsaws), *common, "--fold", "1", "--model", "ensemble",
                  "--curve-every", "1", "--out", str(tmp_path / "curve"))
    assert curve.returncode == 2 and "--curve-every" in curve.stderr and "ensemble" in curve.stderr
    assert not (tmp_path / "curve").exists()
