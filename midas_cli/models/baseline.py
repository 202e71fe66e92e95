"""Per-frame baselines: every frame classified on its own features, no temporal context.

``baseline`` is multinomial logistic regression (one linear layer over the normalised frame features,
written as a 1x1 convolution over time); ``baseline-mlp`` a small MLP (one hidden ReLU layer). Both
take the same inputs as the sequence models (``x`` (B, D, T), ``mask`` (B, T)) and train in the same loop
with frame-wise cross-entropy, so every table can measure the temporal models against something simple.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn


@dataclass
class BaselineConfig:
    in_features: int
    n_classes: int
    hidden: int = 0  # 0 = logistic regression; > 0 = MLP with one hidden layer of this width
    dropout: float = 0.0


class FrameBaseline(nn.Module):
    """Input ``x`` (B, D, T) float, ``mask`` (B, T) bool; output logits (1, B, C, T) (one "stage")."""

    def __init__(self, cfg: BaselineConfig) -> None:
        super().__init__()
        self.cfg = cfg
        if cfg.hidden > 0:
            self.net = nn.Sequential(nn.Conv1d(cfg.in_features, cfg.hidden, 1), nn.ReLU(), nn.Dropout(cfg.dropout),
                                     nn.Conv1d(cfg.hidden, cfg.n_classes, 1))
        else:
            self.net = nn.Conv1d(cfg.in_features, cfg.n_classes, 1)  # = nn.Linear applied to every frame

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        m = mask.unsqueeze(1).to(x.dtype)  # (B, T) -> (B, 1, T)
        return (self.net(x) * m).unsqueeze(0)  # (B, C, T) -> (1, B, C, T)

    def loss(self, stages: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Frame-wise cross-entropy; ``target`` (B, T) long, -1 = ignore."""
        logits = stages[-1]
        return F.cross_entropy(logits.transpose(1, 2).reshape(-1, logits.shape[1]),  # (B*T, C)
                               target.reshape(-1), ignore_index=-1)

    @staticmethod
    def frame_logits(stages: torch.Tensor) -> torch.Tensor:
        return stages[-1]
