"""Hyperparameters of the residual MLP (``models/residual_mlp.py``), without torch: a calibration
options object can name them in processes that never train or load an MLP."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class MLPConfig:
    """Hyperparameters (paper defaults). ``batch_size`` is not stated in the paper; 1024 keeps 15-fold
    cross-validation over a dataset within minutes on 2 CPU cores."""

    hidden: tuple[int, ...] = (16, 16)
    dropout: float = 0.5
    lr: float = 0.005
    weight_decay: float = 1.5
    epochs: int = 50
    batch_size: int = 1024
    seed: int = 0
