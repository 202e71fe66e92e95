"""The small MLP of the paper's Appendix A.2 (table "Hyperparameters ... residual MLP model"), in torch (CPU).

Two hidden layers of 16, ReLU, dropout 0.5; objective RMSE; Adam, lr 0.005, L2 weight decay 1.5
(torch's Adam ``weight_decay``, on every parameter); 50 epochs. Used two ways: the residual
f(p_T; phi) added to a rigid fit (EmHT -> MTM/PSM), and the direct camera -> MTM mapping (A.3).
Inputs and outputs are standardised with statistics of the training data, stored with the weights.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from midas_cli.errors import SessionError
from midas_cli.models.mlp_config import MLPConfig
from midas_cli.models.torch_io import load_weights_only


class MLP(nn.Module):
    """inputs -> [Linear -> ReLU -> Dropout] x len(hidden) -> Linear -> outputs."""

    def __init__(self, inputs: int, outputs: int, hidden: tuple[int, ...], dropout: float) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = inputs
        for size in hidden:
            layers += [nn.Linear(width, size), nn.ReLU(), nn.Dropout(dropout)]
            width = size
        layers.append(nn.Linear(width, outputs))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, inputs) -> (B, outputs)
        return self.net(x)


@dataclass
class FittedMLP:
    """A trained MLP with its standardisation: y = net((x - x_mean) / x_std) * y_std + y_mean."""

    model: MLP
    config: MLPConfig
    x_mean: np.ndarray
    x_std: np.ndarray
    y_mean: np.ndarray
    y_std: np.ndarray
    final_rmse: float

    def predict(self, x: np.ndarray) -> np.ndarray:
        """x (N, inputs) -> (N, outputs); rows with NaN give NaN."""
        out = np.full((len(x), len(self.y_mean)), np.nan)
        ok = np.isfinite(x).all(axis=1)
        if ok.any():
            self.model.eval()
            with torch.no_grad():
                z = torch.as_tensor((x[ok] - self.x_mean) / self.x_std, dtype=torch.float32)
                out[ok] = self.model(z).numpy() * self.y_std + self.y_mean
        return out

    def describe(self) -> dict[str, Any]:
        """JSON-able description (everything but the weights)."""
        return {"config": {**asdict(self.config), "hidden": list(self.config.hidden)},
                "x_mean": self.x_mean.tolist(), "x_std": self.x_std.tolist(), "y_mean": self.y_mean.tolist(),
                "y_std": self.y_std.tolist(), "final_train_rmse_std_units": self.final_rmse}


def train_mlp(x: np.ndarray, y: np.ndarray, config: MLPConfig = MLPConfig(), center_output: bool = True) -> FittedMLP:
    """Fit y (N, outputs) from x (N, inputs) minimising RMSE of the standardised outputs.

    ``center_output`` False keeps y_mean = 0 (a residual whose mean belongs to the rigid part).
    """
    ok = np.isfinite(x).all(axis=1) & np.isfinite(y).all(axis=1)
    x, y = x[ok], y[ok]
    if len(x) < 10:
        raise SessionError(f"too few paired samples to train the MLP ({len(x)}); need at least 10")
    torch.manual_seed(config.seed)
    x_mean, x_std = x.mean(axis=0), _safe_std(x)
    y_mean = y.mean(axis=0) if center_output else np.zeros(y.shape[1])
    y_std = _safe_std(y)
    xs = torch.as_tensor((x - x_mean) / x_std, dtype=torch.float32)
    ys = torch.as_tensor((y - y_mean) / y_std, dtype=torch.float32)
    model = MLP(x.shape[1], y.shape[1], config.hidden, config.dropout)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a 16-unit network: thread hand-offs cost more than they save
    try:
        final = _fit(model, xs, ys, config)
    finally:
        torch.set_num_threads(threads)
    return FittedMLP(model, config, x_mean, x_std, y_mean, y_std, final)


def _fit(model: MLP, xs: torch.Tensor, ys: torch.Tensor, config: MLPConfig) -> float:
    optimiser = torch.optim.Adam(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    generator = torch.Generator().manual_seed(config.seed)
    model.train()
    loss = torch.tensor(float("nan"))
    for _ in range(config.epochs):
        order = torch.randperm(len(xs), generator=generator)
        for start in range(0, len(xs), config.batch_size):
            batch = order[start : start + config.batch_size]
            loss = torch.sqrt(torch.mean((model(xs[batch]) - ys[batch]) ** 2))  # RMSE objective
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
    return float(loss.detach())


def save_mlp(fitted: FittedMLP, path: Path) -> None:
    """Weights only (a plain state dict of tensors), loadable with ``torch.load(weights_only=True)``."""
    torch.save(fitted.model.state_dict(), path)


def load_mlp(path: Path, description: dict[str, Any]) -> FittedMLP:
    """Rebuild a FittedMLP from its weights file and ``describe()`` dictionary."""
    cfg = dict(description["config"])
    config = MLPConfig(**{**cfg, "hidden": tuple(cfg["hidden"])})
    y_mean = np.asarray(description["y_mean"])
    x_mean = np.asarray(description["x_mean"])
    model = MLP(len(x_mean), len(y_mean), config.hidden, config.dropout)
    state = load_weights_only(path, "MLP weights")
    try:
        model.load_state_dict(state)
    except (RuntimeError, TypeError, AttributeError) as exc:  # not this MLP's state dict
        raise SessionError(f"cannot load MLP weights {path}: {exc}") from exc
    return FittedMLP(model, config, x_mean, np.asarray(description["x_std"]), y_mean,
                     np.asarray(description["y_std"]), float(description.get("final_train_rmse_std_units", np.nan)))


def _safe_std(values: np.ndarray) -> np.ndarray:
    std = values.std(axis=0)
    return np.where(std > 1e-9, std, 1.0)
