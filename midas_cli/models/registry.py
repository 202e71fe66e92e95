"""The gesture models, one entry each: everything midas knows about a model is here.

An entry holds the model's name (``--model``), its title in the ablation tables, its line in the
``--model`` help, its training recipe and how to build its config and network. Adding a model is one
entry below plus its module (a network and its ``@dataclass`` config). The builders import their
module only when called, so reading this table (``midas train --help``) never imports torch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from midas_cli.errors import ConfigError

# What a run.json written before these TrainConfig fields existed meant by leaving them out (runs are
# compared with the settings asked for when cross-validation or an ablation resumes).
LEGACY_TRAIN_CONFIG = {"causal": False, "min_segment": "none", "curve_every": 0, "delay_s": 0.0, "augment_shift": 0.0,
                       "augment_features": "pos", "grammar": "none",
                       "decode_lag_s": 0.0}
# A builder: (modality dims, class count) -> (network class, its default config for those inputs).
Builder = Callable[[dict[str, int], int], tuple[Callable[[Any], Any], Any]]


@dataclass(frozen=True)
class Recipe:
    """How a model is trained where TrainConfig leaves a field None: epochs, batch size, Adam learning
    rate, which epoch's weights are kept (``last``; ``best-val``: the best validation frame
    accuracy's, without a validation set the last epoch's; ``average``: the mean of the second half's,
    models/averaging.py), and the training
    inputs' shift augmentation (``augment_shift`` standard deviations of the ``augment_features`` columns,
    models/augment.py; 0: none). An ensemble's epochs, batch size and lr are None: each member trains with
    its own recipe's; its selection ("average") and shift apply to every member."""

    epochs: int | None
    batch_size: int | None
    lr: float | None
    selection: str | None
    augment_shift: float = 0.0
    augment_features: str = "pos"


@dataclass(frozen=True)
class ModelEntry:
    """One gesture model: ``name`` (``--model``), ``title`` (ablation tables), ``summary`` (its words in
    the ``--model`` help, empty for none), ``recipe`` and ``build`` (see :data:`Builder`)."""

    name: str
    title: str
    summary: str
    recipe: Recipe
    build: Builder


def _mstcn(dims: dict[str, int], n_classes: int) -> tuple[Callable[[Any], Any], Any]:
    from midas_cli.models.mstcn import MSTCN, MSTCNConfig

    return MSTCN, MSTCNConfig(in_features=sum(dims.values()), n_classes=n_classes)


def _transformer(refined: bool) -> Builder:
    """The MTRSAP-style transformer, with MS-TCN++ refinement stages or (``refined`` False) without."""

    def build(dims: dict[str, int], n_classes: int) -> tuple[Callable[[Any], Any], Any]:
        from midas_cli.models.transformer import GestureTransformer, TransformerConfig

        plain = {} if refined else {"refinement_stages": 0, "smoothing_weight": 0.0}
        return GestureTransformer, TransformerConfig(modality_dims=dict(dims), n_classes=n_classes, **plain)

    return build


def _ensemble(dims: dict[str, int], n_classes: int) -> tuple[Callable[[Any], Any], Any]:
    from functools import partial

    from midas_cli.models.ensemble import Ensemble, EnsembleConfig

    return partial(Ensemble, entry=model_entry), EnsembleConfig(modality_dims=dict(dims), n_classes=n_classes)


def _baseline(hidden: int) -> Builder:
    """The per-frame baseline: logistic regression (``hidden`` 0) or an MLP with one hidden layer."""

    def build(dims: dict[str, int], n_classes: int) -> tuple[Callable[[Any], Any], Any]:
        from midas_cli.models.baseline import BaselineConfig, FrameBaseline

        return FrameBaseline, BaselineConfig(sum(dims.values()), n_classes, hidden=hidden)

    return build


# MS-TCN++ trains as in the official code (sj-li/MS-TCN2 main.py, train.sh): Adam lr 5e-4, batch size 1,
# the last epoch's weights (no model selection), but for 20 epochs, not the official 100, with the
# training inputs' positions and orientations shifted per sequence (models/augment.py, SD 1). Chosen on
# both JIGSAWS development tasks (all LOUO folds, learning curves every 10 epochs, BENCHMARKS.md; raw
# pooled accuracy / mean edit): without the shift the curves reach their plateau by epoch 50 (Knot Tying
# 78.5 / 78.6, Needle Passing 67.3 / 75.3; 79.3 and 66.8 at 100); with it they peak by epoch 20 (Knot Tying
# 78.1 / 82.2, Needle Passing 71.2 / 79.6; seed 1: 77.6 / 81.5 and 72.2 / 80.4) and drift down after (Knot
# Tying 76.4 / 81.2 at 50, Needle Passing 70.3 / 80.3): a point less accuracy on Knot Tying, four more on
# Needle Passing (user B 66.9 against 43.3), better segments on both, in two fifths of the time.
# ``--epochs 100 --augment-shift 0`` gives the official recipe. The
# transformers keep midas's earlier recipe, lr 1e-3, batches of 4, the weights of the best validation
# epoch, but the refined transformer trains 10 epochs, not 50: on both JIGSAWS development tasks (all LOUO folds, learning curves every 5
# epochs, BENCHMARKS.md) its test accuracy peaked at epoch 10 and fell after it (Knot Tying 77.2 at 10,
# 74.4 at 50; Needle Passing 69.5 and 62.0), with the edit score too; and it shifts its inputs as MS-TCN++
# does (defaults with the clean-up, pooled, mean of seeds 0 and 1: Needle Passing 72.7 / 79.8 against 68.6 /
# 75.9 without, Knot Tying 75.6 / 78.5 against 76.5 / 76.9). transformer-plain was not measured and keeps
# 50 epochs, no shift. The per-frame baselines: lr 1e-2 (logistic regression), 1e-3 (MLP), 50 epochs. The
# ensemble (the default model, models/ensemble.py) has no recipe of its own but the shift and the weights: each
# member trains with its own epochs, batch size and lr, and keeps the mean of its weights over the second half
# of its epochs (models/averaging.py; README, "--weights average"; all folds, pooled, with the --grammar
# clean-up, seed 0: Knot Tying 80.6 / 89.4 against 78.6 / 87.8 with the last epoch's weights, four members
# then; its members now: models/ensemble.py MEMBERS). The order is the help's.
ENTRIES = (
    ModelEntry("mstcn", "MS-TCN++", "MS-TCN++", Recipe(20, 1, 5e-4, "last", 1.0, "pos,ori"), _mstcn),
    ModelEntry("transformer", "MTRSAP", "MTRSAP-style with MS-TCN++ refinement stages",
               Recipe(10, 4, 1e-3, "best-val", 1.0, "pos,ori"), _transformer(refined=True)),
    ModelEntry("transformer-plain", "MTRSAP (plain)", "without", Recipe(50, 4, 1e-3, "best-val"),
               _transformer(refined=False)),
    ModelEntry("ensemble", "Ensemble (2 MS-TCN++ + MTRSAP)", "two MS-TCN++ and a transformer averaged",
               Recipe(None, None, None, "average", 1.0, "pos,ori"), _ensemble),
    ModelEntry("baseline", "Baseline (LR)", "per-frame logistic regression", Recipe(50, 4, 1e-2, "best-val"),
               _baseline(hidden=0)),
    ModelEntry("baseline-mlp", "Baseline (MLP)", "", Recipe(50, 4, 1e-3, "best-val"), _baseline(hidden=64)),
)
MODELS: dict[str, ModelEntry] = {entry.name: entry for entry in ENTRIES}


def model_entry(name: str) -> ModelEntry:
    """The entry of model ``name``; ConfigError naming the known models for another."""
    if name not in MODELS:
        raise ConfigError(f"--model {name!r} is unknown (expected one of {', '.join(MODELS)})")
    return MODELS[name]


def model_help() -> str:
    """The ``--model`` help: every model with its summary, in table order."""
    names = [f"{e.name} ({e.summary})" if e.summary else e.name for e in ENTRIES]
    return f"{', '.join(names[:-1])} or {names[-1]}." if len(names) > 1 else f"{names[0]}."
