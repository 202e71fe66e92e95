"""Done-when check of issue 7 on a simulated Raven-II peg-transfer dataset (10 trials, `midas simulate`):
MS-TCN++ and the transformer trained on EmHT reach frame accuracy >= 0.80 under the gesture split, and a
shuffled-label control stays near chance (the pipeline learns from the signal, not from structure).

Sized to prove that and no more: on 10 trials (3 subjects) MS-TCN++ passes validation accuracy 0.95
by epoch 4-5 and the transformer by epoch 3-4, so 8 epochs leave a margin (test accuracy 1.0 and 0.975
with seed 0, 1.0 and 1.0 with seed 1; the control 0.23, chance about 1/8). The earlier 15 trials x 15
epochs gave the same verdicts at about three times the cost.

Issue 19: MS-TCN++ now trains with its published recipe (batch size 1, last epoch's weights) and the
default transformer carries one MS-TCN++ refinement stage; both still pass at 8 epochs (seed 0: test
accuracy 0.964 for MS-TCN++, its last epoch's weights, and 0.977 for the transformer). (With three
refinement stages the transformer stalled near 0.78 here, even after 16 epochs: models/transformer.py.)

The dataset is `--difficulty easy` (every subject moves alike): the point here is the training
mechanics, not how hard the data is. So the inputs are not shifted (``augment_shift=0``): MS-TCN++'s
recipe shifts positions and orientations (chosen on real kinematics, where users sit apart), which on
this set, where the positions give the gesture away, slows it (seed 0: 0.756 at 8 epochs, 0.894 at its
recipe's 20, 1.0 at 14; 0.963 at 8 without the shift). How far the default `real` simulator pulls models below 1.0 under
LOUO (MS-TCN++ against a per-frame logistic regression) is measured in README ("Simulated data vs real
data") with `midas train gestures --model baseline --split louo --fold all`."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from helpers.cli import midas
from midas_cli.analysis.align import align_and_write
from midas_cli.models.data import DatasetConfig
from midas_cli.models.train import TrainConfig, train_run

# Training on CPU: about 2 min for the three runs on a quiet 2-core machine, several times that under load.
pytestmark = [pytest.mark.slow, pytest.mark.timeout(1200)]

EMHT = DatasetConfig(("emht",), ("pos", "ori", "vel"), exclude_clutch=True)
EPOCHS = 8


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """One intra-op thread: these small convolutions gain little from a second one, and on a shared
    2-core machine two threads waiting on each other ran slower than one (5.9 vs 4.3 s an epoch)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def raven(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("raven10")
    result = midas("simulate", "dataset", "--platform", "raven-ii", "--trials", "10", "--subjects", "3",
                   "--seed", "3", "--difficulty", "easy", "--out", str(root), "--jobs", "2", timeout=1800,
                   check=True)
    sessions = [Path(line) for line in result.stdout.split() if line.strip()]
    assert len(sessions) == 10
    for session in sessions:
        align_and_write(session)
    return sessions


@pytest.mark.parametrize("model", ["mstcn", "transformer"])
def test_emht_gesture_split_reaches_080(raven, tmp_path, model):
    result = train_run(raven, EMHT, TrainConfig(model=model, epochs=EPOCHS, seed=0, augment_shift=0.0), tmp_path / model)
    summary = result.metrics["test"]["summary"]
    assert summary["accuracy"] >= 0.80, summary


def test_shuffled_labels_stay_near_chance(raven, tmp_path):
    result = train_run(raven, EMHT, TrainConfig(model="transformer", epochs=EPOCHS, seed=0, shuffle_labels=True),
                       tmp_path / "control")
    summary = result.metrics["test"]["summary"]
    n_classes = len(result.metrics["test"]["per_class"])  # S1..S7 and Idle: chance about 1/8
    assert summary["accuracy"] < 0.35, (summary, n_classes)
