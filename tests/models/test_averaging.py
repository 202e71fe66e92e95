"""``--weights average`` (models/averaging.py): the kept weights are the mean of the second half's, and
training itself is exactly the run with the last epoch's weights."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from helpers.cli import midas
from helpers.gesture_sessions import write_gesture_dataset
from midas_cli.errors import ConfigError
from midas_cli.models.averaging import WeightAverage
from midas_cli.models.sequences import Sequences
from midas_cli.models.train import TrainConfig, build_model, fit

DIMS, CLASSES = {"emht": 4}, 3
NONE = Sequences([], [], [])
SMALL = {"pg_layers": 3, "refinement_stages": 1, "refinement_layers": 3, "feature_maps": 8, "dropout": 0.5}


def _train_data() -> Sequences:
    rng = np.random.default_rng(3)
    xs = [rng.normal(size=(t, 4)).astype(np.float32) for t in (37, 52, 29)]
    ys = [np.digitize(x[:, 0], [-0.4, 0.4]).astype(np.int64) for x in xs]
    return Sequences([(f"t{i}", 0, len(x)) for i, x in enumerate(xs)], xs, ys)


def _fit(selection: str, epochs: int, snapshots: list | None = None) -> tuple[torch.nn.Module, list[dict]]:
    torch.manual_seed(0)
    model = build_model("mstcn", DIMS, CLASSES, SMALL)[0]
    config = TrainConfig(model="mstcn", epochs=epochs, batch_size=1, lr=3e-3, selection=selection, seed=2)

    def keep(epoch: int, _: int, record: dict) -> None:
        if snapshots is not None:
            snapshots.append({k: v.detach().clone() for k, v in model.state_dict().items()})

    return model, fit(model, _train_data(), NONE, config, torch.device("cpu"), progress=keep)


@pytest.mark.parametrize("epochs,averaged", [(5, [2, 3, 4]), (4, [2, 3]), (1, [0])])
def test_average_keeps_the_mean_of_the_second_half_and_trains_as_last_does(epochs, averaged):
    snapshots: list[dict] = []
    last, last_history = _fit("last", epochs, snapshots)
    mean, mean_history = _fit("average", epochs)
    # the same training: dropout on, yet every epoch's loss is identical (averaging draws no random numbers)
    assert [h["loss"] for h in mean_history] == [h["loss"] for h in last_history]
    for key, value in mean.state_dict().items():
        expected = torch.stack([snapshots[i][key] for i in averaged]).mean(dim=0)
        torch.testing.assert_close(value, expected, rtol=1e-5, atol=1e-6, msg=key)
    if epochs > 1:  # and it is not the last epoch's weights
        assert any(not torch.allclose(a, b) for a, b in zip(mean.state_dict().values(), last.state_dict().values()))


def test_integer_state_keeps_its_last_value_and_no_epoch_leaves_the_model_alone():
    model = torch.nn.Linear(2, 2)
    model.register_buffer("steps", torch.tensor(0))
    average = WeightAverage(epochs=2)
    for epoch, value in ((1, 9.0), (2, 1.0)):
        torch.nn.init.constant_(model.weight, value)
        model.steps += 1
        average.after_epoch(model, epoch)
    torch.nn.init.constant_(model.weight, 5.0)
    average.apply(model)
    assert torch.all(model.weight == 1.0) and int(model.steps) == 2  # epoch 1 is the first half: left out
    untouched = torch.nn.Linear(2, 2)
    before = untouched.weight.detach().clone()
    WeightAverage(epochs=0).apply(untouched)
    assert torch.equal(untouched.weight, before)


def test_an_unknown_weights_choice_is_refused():
    with pytest.raises(ConfigError, match="--weights"):
        TrainConfig(model="mstcn", selection="median")


def test_cli_records_the_choice_for_every_member_and_refuses_a_bad_one(tmp_path):
    sessions = write_gesture_dataset(tmp_path / "data", n_trials=4, subjects=2, n_frames=120)
    args = ["train", "gestures", *map(str, sessions), "--model", "ensemble", "--modalities", "emht",
            "--features", "pos,vel", "--epochs", "2", "--accelerator", "cpu", "--split", "louo"]
    result = midas(*args, "--weights", "average", "--out", str(tmp_path / "run"))
    assert result.returncode == 0, result.stderr
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["train_config"]["selection"] == "average"
    assert [m["selection"] for m in run["recipe"]["members"]] == ["average"] * 3
    bad = midas(*args, "--weights", "best", "--out", str(tmp_path / "bad"))
    assert bad.returncode != 0 and not (tmp_path / "bad").exists()
    assert "--weights" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
