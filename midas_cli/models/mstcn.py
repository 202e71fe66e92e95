"""MS-TCN++ (Li, Abu Farha, Liu, Cheng, Gall: "MS-TCN++: Multi-Stage Temporal Convolutional Network for
Action Segmentation", TPAMI 2020), frame-wise over whole sequences.

As published: a prediction-generation stage of 11 dual-dilated layers (each layer adds a dilation
2^(L-1-l) and a dilation 2^l 3-tap convolution, fuses them with a 1x1 convolution, ReLU, dropout,
residual), then 3 refinement stages of 10 dilated residual layers (dilation 2^l) fed with the softmax
of the previous stage, 64 feature maps. Loss per stage: cross-entropy + 0.15 x the truncated MSE of
the log-probabilities of consecutive frames (clamped at tau^2 with tau = 4, gradient stopped through
the previous frame). Padding frames are masked (mask (B, 1, T), 1 = real frame) so batches of
different lengths give the same result as one sequence at a time.

Audited against the official code (sj-li/MS-TCN2 ``model.py``, ``main.py``, ``train.sh``): layer counts,
dilations, dropout (``nn.Dropout()`` = 0.5), the 1x1 fusion, the softmax between stages and the loss
are the same. The training recipe that goes with it (``registry.py``, entry "mstcn"): Adam lr 5e-4,
batch size 1, the last epoch's weights, 100 epochs officially (midas's default is 50, chosen on the
JIGSAWS development tasks: ``registry.py``). Two deliberate differences, both neutral at batch
size 1: the official model masks nothing (its batches of one have no padding) and its smoothing term
is a mean over every position of the padded batch, padding included; here padding is masked and the
mean is over the real frame pairs, so a batch of several sequences trains like the same sequences alone.

Causal variant (``causal=True``, ``midas train gestures --causal``): every dilated convolution looks only
back, its taps at t - 2d, t - d and t (zero padding on the left only), so the output at frame t depends on
frames <= t alone and the model can run live, one frame at a time (``models/streaming.py``). The 1x1
convolutions, the softmax between stages and the mask are per frame already; padding frames sit at the
end of a sequence, after every real frame, so they never reach a real frame's output.

Delayed causal variant (``delay`` frames > 0, ``train gestures --causal --delay SECONDS``): the output for
frame t is computed at frame t + delay, from the frames <= t + delay: the network runs over the sequence
with ``delay`` zero frames (the normalised features' mean) appended, its mask extended over them, and its
outputs shifted back by ``delay`` (:func:`look_ahead`, :func:`shifted_back`). Live, that is a gesture shown
``delay`` frames late, with that much of what follows it seen; at the end of a recording the same zero
frames give the last frames their labels, so live and offline agree frame for frame. Batches still equal
sequences alone: a shorter sequence's zeros run on past its end into the batch padding, as they would alone.

How it is computed (the same network and gradients, up to float rounding; the parameters and checkpoints
are those of the layers as written): a dual-dilated layer's two 3-tap convolutions and its 1x1 fusion are
all linear, so the fused output is one matrix product over the input's distinct taps (t, t +- d_small,
t +- d_large: five, not six, and only those within the sequence), with the effective weights formed from
the layer's own each step (:meth:`DualDilatedLayer.forward`): 2.7x fewer multiply-adds in the
prediction-generation stage and its backward pass. The refinement stages' dilated convolutions are one
product over their shifted input too (:class:`DilatedConv`). Dropout draws uniform numbers and compares them
(:class:`Dropout`) rather than torch's per-element Bernoulli draws, 2.6x slower on the CPU, and applies the
mask as one float product. Together with fused Adam (``train.fit``) an epoch takes ~0.7x the time of the
published layout (BENCHMARKS.md, "MS-TCN++: midas against a reference implementation"); the last three
changes (the refinement convolutions, the dropout mask, the fused weights formed with one product per
convolution) took a training step to ~0.95x (2026-11-28, Knot Tying fold B, old and new code alternating
in one process over 40 four-step rounds, twice: 0.943 and 0.949).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn


@dataclass
class MSTCNConfig:
    in_features: int
    n_classes: int
    pg_layers: int = 11
    refinement_stages: int = 3
    refinement_layers: int = 10
    feature_maps: int = 64
    dropout: float = 0.5
    smoothing_weight: float = 0.15
    tau: float = 4.0
    causal: bool = False  # taps at t - 2d, t - d, t instead of t - d, t, t + d
    delay: int = 0  # causal: frame t labelled from the frames <= t + delay (look_ahead)


def look_ahead(x: torch.Tensor, mask: torch.Tensor, delay: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``x`` (B, D, T) and ``mask`` (B, T) with ``delay`` zero frames appended, the mask True over the
    ``delay`` frames after each sequence's last real one (the input of a delayed causal network)."""
    if delay < 0:
        raise ValueError(f"delay must be >= 0 frames, got {delay}")
    if not delay:
        return x, mask
    x = F.pad(x, (0, delay))  # (B, D, T) -> (B, D, T + delay)
    mask = F.pad(mask, (0, delay), value=False)
    return x, mask | F.pad(mask, (delay, 0), value=False)[:, :-delay]


def shifted_back(stages: torch.Tensor, delay: int) -> torch.Tensor:
    """Outputs (..., T + delay) computed at frames t + delay -> (..., T): the ones for frames t."""
    return stages[..., delay:] if delay else stages


class DilatedConv(nn.Conv1d):
    """3-tap dilated convolution with zero "same" padding (taps t - d, t, t + d), or with ``causal`` zero
    padding on the left only (taps t - 2d, t - d, t). Computed as one matrix product over the input shifted
    by each tap's offset (zeros outside the sequence), ~10 % faster on the CPU than torch's convolution
    at 64 maps, batch 1 (forward and backward). A tap whose offset reaches past the sequence only ever sees
    padding, so it is left out: the same output without multiplying zeros."""

    def __init__(self, maps: int, dilation: int, causal: bool = False) -> None:
        super().__init__(maps, maps, 3, padding=0 if causal else dilation, dilation=dilation)
        self.causal = causal

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        length = x.shape[-1]
        taps = [(tap, offset) for tap, offset in enumerate(tap_offsets(self)) if abs(offset) < length]
        if len(taps) == 1:  # only the tap at frame t sees the sequence
            return F.conv1d(x, self.weight[:, :, taps[0][0]:taps[0][0] + 1], self.bias)
        shifted = shifted_input(x, [offset for _, offset in taps])  # (B, nM, T)
        kept = self.weight if len(taps) == 3 else self.weight[:, :, [tap for tap, _ in taps]]
        weight = kept.transpose(1, 2).reshape(kept.shape[0], -1)  # (M, nM), tap-major as ``shifted``
        return torch.matmul(weight, shifted) + self.bias[:, None]


class Dropout(nn.Dropout):
    """``nn.Dropout`` (same ``p``, same scaling, inverted dropout) with its mask from uniform draws compared
    with the keep probability: the same distribution, 2.6x faster than ``bernoulli_`` on the CPU, and
    vmap's ``randomness="different"`` draws per model as before."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.training or self.p == 0.0:
            return x
        if self.p >= 1.0:
            return x * 0.0
        keep = 1.0 - self.p
        scaled = (torch.rand_like(x) < keep).to(x.dtype).mul_(1.0 / keep)  # 0 or 1/keep, in x's dtype (fp16 too)
        return x * scaled  # one product forward and one backward (a bool mask is converted in each)


def shifted_input(x: torch.Tensor, offsets: list[int]) -> torch.Tensor:
    """``x`` (B, M, T) shifted by each of the sorted frame ``offsets`` (zeros outside the sequence), stacked
    offset-major along the maps: (B, len(offsets) * M, T), the input of a convolution as one product."""
    length = x.shape[-1]
    left, right = max(0, -offsets[0]), max(0, offsets[-1])
    padded = F.pad(x, (left, right))  # (B, M, left + T + right)
    return torch.cat([padded[..., left + o:left + o + length] for o in offsets], dim=1)


def tap_offsets(conv: DilatedConv) -> list[int]:
    """The frame offsets of a dilated convolution's taps 0, 1, 2 relative to the output frame t."""
    d = conv.dilation[0]
    return [-2 * d, -d, 0] if conv.causal else [-d, 0, d]


class DualDilatedLayer(nn.Module):
    """Prediction-generation layer: two dilations (one shrinking, one growing with depth) fused by 1x1."""

    def __init__(self, maps: int, dilation_small: int, dilation_large: int, dropout: float,
                 causal: bool = False) -> None:
        super().__init__()
        self.conv_large = DilatedConv(maps, dilation_large, causal)
        self.conv_small = DilatedConv(maps, dilation_small, causal)
        self.fusion = nn.Conv1d(2 * maps, maps, 1)
        self.dropout = Dropout(dropout)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """``fusion(cat(conv_large(x), conv_small(x)))`` computed as one product: fusion's halves times each
        convolution's taps, summed per distinct frame offset, applied to the input shifted by those offsets
        (zeros outside the sequence; a tap whose offset reaches past the sequence only ever sees zeros and is
        left out, as ``DilatedConv`` does)."""
        length, maps = x.shape[-1], x.shape[1]
        fusion = self.fusion.weight[:, :, 0]  # (M, 2M)
        weights: dict[int, torch.Tensor] = {}
        for conv, half in ((self.conv_large, fusion[:, :maps]), (self.conv_small, fusion[:, maps:])):
            taps = (half @ conv.weight.flatten(1)).view_as(conv.weight)  # (M, M, 3): one product for the 3 taps
            for tap, offset in enumerate(tap_offsets(conv)):
                if abs(offset) < length:
                    w = taps[:, :, tap]  # (M, M)
                    weights[offset] = weights[offset] + w if offset in weights else w
        bias = fusion[:, :maps] @ self.conv_large.bias + fusion[:, maps:] @ self.conv_small.bias + self.fusion.bias
        offsets = sorted(weights)
        shifted = shifted_input(x, offsets)  # (B, nM, T)
        fused = torch.matmul(torch.cat([weights[o] for o in offsets], dim=1), shifted) + bias[:, None]
        return (x + self.dropout(F.relu(fused))) * mask


class DilatedResidualLayer(nn.Module):
    """Refinement layer: dilated 3-tap convolution, ReLU, 1x1, dropout, residual."""

    def __init__(self, maps: int, dilation: int, dropout: float, causal: bool = False) -> None:
        super().__init__()
        self.conv_dilated = DilatedConv(maps, dilation, causal)
        self.conv_1x1 = nn.Conv1d(maps, maps, 1)
        self.dropout = Dropout(dropout)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return (x + self.dropout(self.conv_1x1(F.relu(self.conv_dilated(x))))) * mask


class PredictionGeneration(nn.Module):
    def __init__(self, cfg: MSTCNConfig) -> None:
        super().__init__()
        n = cfg.pg_layers
        self.conv_in = nn.Conv1d(cfg.in_features, cfg.feature_maps, 1)
        self.layers = nn.ModuleList(
            DualDilatedLayer(cfg.feature_maps, 2 ** i, 2 ** (n - 1 - i), cfg.dropout, cfg.causal) for i in range(n))
        self.conv_out = nn.Conv1d(cfg.feature_maps, cfg.n_classes, 1)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        h = self.conv_in(x) * mask  # (B, D, T) -> (B, M, T)
        for layer in self.layers:
            h = layer(h, mask)
        return self.conv_out(h) * mask  # (B, C, T)


class Refinement(nn.Module):
    def __init__(self, cfg: MSTCNConfig) -> None:
        super().__init__()
        self.conv_in = nn.Conv1d(cfg.n_classes, cfg.feature_maps, 1)
        self.layers = nn.ModuleList(
            DilatedResidualLayer(cfg.feature_maps, 2 ** i, cfg.dropout, cfg.causal)
            for i in range(cfg.refinement_layers))
        self.conv_out = nn.Conv1d(cfg.feature_maps, cfg.n_classes, 1)

    def forward(self, probs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        h = self.conv_in(probs) * mask  # (B, C, T) -> (B, M, T)
        for layer in self.layers:
            h = layer(h, mask)
        return self.conv_out(h) * mask  # (B, C, T)


class MSTCN(nn.Module):
    """Input ``x`` (B, D, T) float, ``mask`` (B, T) bool; output logits per stage (S, B, C, T)."""

    def __init__(self, cfg: MSTCNConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.generation = PredictionGeneration(cfg)
        self.refinements = nn.ModuleList(Refinement(cfg) for _ in range(cfg.refinement_stages))

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        x, mask = look_ahead(x, mask, self.cfg.delay)
        m = mask.unsqueeze(1).to(x.dtype)  # (B, T) -> (B, 1, T)
        logits = self.generation(x, m)
        stages = [logits]
        for refinement in self.refinements:
            logits = refinement(F.softmax(logits, dim=1) * m, m)
            stages.append(logits)
        return shifted_back(torch.stack(stages), self.cfg.delay)  # (S, B, C, T)

    def loss(self, stages: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Sum over stages of CE + smoothing_weight * truncated MSE. ``target`` (B, T) long, -1 = ignore."""
        return segmentation_loss(stages, target, mask, self.cfg.smoothing_weight, self.cfg.tau)

    @staticmethod
    def frame_logits(stages: torch.Tensor) -> torch.Tensor:
        """The last stage's logits (B, C, T): the prediction."""
        return stages[-1]


def smoothing_loss(logits: torch.Tensor, mask: torch.Tensor, tau: float) -> torch.Tensor:
    """MS-TCN's truncated MSE over frame-to-frame log-probability changes of one stage.

    ``logits`` (B, C, T), ``mask`` (B, T) bool. Per real frame pair (t-1, t) and class c:
    min((log p_t,c - log p_t-1,c)^2, tau^2), the earlier frame's log-probability detached (gradient
    only pulls frame t towards t-1, as in the official code); the mean over real pairs x classes.
    """
    pair_mask = (mask[:, 1:] & mask[:, :-1]).unsqueeze(1).to(logits.dtype)  # (B, 1, T-1): both frames real
    log_p = F.log_softmax(logits, dim=1)
    mse = torch.clamp((log_p[:, :, 1:] - log_p.detach()[:, :, :-1]) ** 2, min=0, max=tau ** 2)  # (B, C, T-1)
    return (mse * pair_mask).sum() / (pair_mask.sum() * logits.shape[1]).clamp(min=1)


def segmentation_loss(stages: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, smoothing_weight: float,
                      tau: float) -> torch.Tensor:
    """Sum over stages (S, B, C, T) of frame-wise cross-entropy (``target`` (B, T), -1 = ignore) plus
    ``smoothing_weight`` x :func:`smoothing_loss` (MS-TCN++: 0.15, tau = 4)."""
    total = stages.new_zeros(())
    for logits in stages:
        total = total + F.cross_entropy(logits.transpose(1, 2).reshape(-1, logits.shape[1]),  # (B*T, C)
                                        target.reshape(-1), ignore_index=-1)
        if smoothing_weight:
            total = total + smoothing_weight * smoothing_loss(logits, mask, tau)
    return total
