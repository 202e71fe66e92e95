"""MTRSAP-style multimodal transformer (Weerasinghe et al., "Multimodal Transformer for Real-time
Surgical Activity Recognition and Prediction", ICRA 2024), frame-wise.

Per modality, a 1-D CNN encoder over time (three same-padded convolutions with ReLU, stride 1 so every
frame keeps its own embedding); the modality embeddings are concatenated and fused by a linear layer
to ``d_model``; a sinusoidal position code is added; a transformer encoder attends over TIME; a linear
head gives per-frame class logits.

What differs from the public implementation, and why: in UVA-DSA/MTRSAP ``models/transtcn.py``
(commit aa11a5b) ``TransformerModel`` builds ``nn.TransformerEncoderLayer(d_model, nhead, dropout)``
without ``batch_first=True`` (PyTorch's default is False) but feeds it ``[batch, time, d]``: PyTorch
reads dimension 0 (the batch of windows) as the sequence, so attention mixes different windows at the
same time step instead of the frames of one window (a later commit of that repository adds a
``batch_first`` argument). Here the sequence is explicitly split into windows of ``window`` frames,
reshaped to ``[batch * n_windows, window, d]`` and given to an encoder built with
``batch_first=True``, so every attention weight connects two frames of the same window; padding
frames are excluded with ``src_key_padding_mask``. The public model also max-pools the window to one
label; this one keeps a label per frame (frame-wise segmentation, like MS-TCN++).
Windows tile the sequence without overlap; the CNN encoders before them see across window borders.

Temporal refinement (the default ``transformer``; ``transformer-plain`` has none): per-window
predictions flicker, above all at window borders, which ruins segmental metrics (edit, F1@k). As in
MS-TCN++, ``refinement_stages`` refinement stages (``mstcn.Refinement``: 10 dilated residual layers,
64 maps, dropout 0.5, receptive field over 2000 frames, so across windows) are stacked on the
softmax of the transformer's frame logits, and every stage is trained with cross-entropy +
``smoothing_weight`` x the truncated MSE smoothing loss (tau = 4). The prediction is the last stage's.
One stage by default, not MS-TCN++'s three: the stages train from scratch together with the
transformer, and deeper stacks converged much later. On the simulated Raven-II EmHT gesture split
(tests/models/test_train_simulated.py data, seed 0, 10 epochs) test accuracy was 0.98 with one stage, 0.88
with two and 0.78 with three (three stages still at 0.78 after 16 epochs); one stage already removes
much of the flicker on a noisy toy task (tests/models/test_models_recipe.py).
The plain variant (``refinement_stages=0, smoothing_weight=0``) is the model above alone, trained with
cross-entropy only, kept for the ablation.

Causal variant (``causal=True``, ``midas train gestures --causal``): the CNN encoders pad on the left only
(a frame's embedding sees the ``kernel_size`` - 1 frames before it), attention is masked to the frames of
the window at or before the query (window position p attends to positions 0..p of its own window, so a
frame costs at most ``window`` attention terms, live as offline) and the refinement stages are MS-TCN++'s
causal ones: the output at frame t depends on frames <= t alone (``models/streaming.py`` runs it frame by
frame). With ``delay`` frames > 0 (``--delay``) it labels frame t from the frames <= t + delay, as the
delayed MS-TCN++ does (``mstcn.look_ahead``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from midas_cli.models.mstcn import MSTCNConfig, Refinement, look_ahead, segmentation_loss, shifted_back


@dataclass
class TransformerConfig:
    modality_dims: dict[str, int]  # input features per modality, in the order the data gives them
    n_classes: int
    cnn_channels: int = 64
    kernel_size: int = 9
    d_model: int = 64
    n_heads: int = 4
    n_layers: int = 2
    ff_dim: int = 128
    window: int = 64
    dropout: float = 0.1
    modality_order: list[str] = field(default_factory=list)
    refinement_stages: int = 1  # MS-TCN++ refinement stages on the frame probabilities; 0 = plain
    refinement_layers: int = 10
    refinement_maps: int = 64
    refinement_dropout: float = 0.5
    smoothing_weight: float = 0.15  # MS-TCN++ smoothing loss weight (lambda); 0 = cross-entropy only
    tau: float = 4.0
    causal: bool = False  # frame t sees frames <= t only (left-padded convolutions, masked attention)
    delay: int = 0  # causal: frame t labelled from the frames <= t + delay (mstcn.look_ahead)

    def __post_init__(self) -> None:
        if not self.modality_order:
            self.modality_order = list(self.modality_dims)


class ModalityEncoder(nn.Module):
    """1-D CNN over time for one modality: (B, D_m, T) -> (B, cnn_channels, T); padding stays zero.
    Same padding, or with ``causal`` kernel - 1 zeros on the left only (frame t sees t - kernel + 1 .. t)."""

    def __init__(self, in_features: int, channels: int, kernel: int, dropout: float, depth: int = 3,
                 causal: bool = False) -> None:
        super().__init__()
        self.convs = nn.ModuleList(nn.Conv1d(in_features if i == 0 else channels, channels, kernel,
                                             padding=0 if causal else kernel // 2) for i in range(depth))
        self.dropout = nn.Dropout(dropout)
        self.left_pad = kernel - 1 if causal else 0

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        h = x * mask  # mask (B, 1, T)
        for conv in self.convs:
            h = self.dropout(F.relu(conv(F.pad(h, (self.left_pad, 0))))) * mask  # (B, K, pad + T) -> (B, K, T)
        return h


def sinusoidal_positions(length: int, d_model: int) -> torch.Tensor:
    """(length, d_model) sine/cosine position code (Vaswani et al.)."""
    position = torch.arange(length, dtype=torch.float32).unsqueeze(1)  # (L, 1)
    rate = torch.exp(torch.arange(0, d_model, 2, dtype=torch.float32) * (-math.log(10000.0) / d_model))
    code = torch.zeros(length, d_model)
    code[:, 0::2] = torch.sin(position * rate)
    code[:, 1::2] = torch.cos(position * rate)[:, : d_model // 2]
    return code


class GestureTransformer(nn.Module):
    """Input ``x`` (B, D, T) with modalities concatenated along D in ``modality_order``; ``mask`` (B, T)
    bool (True = real frame). Output logits per stage (S, B, C, T): the transformer's, then one per
    refinement stage (S = 1 for the plain variant)."""

    def __init__(self, cfg: TransformerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoders = nn.ModuleDict({name: ModalityEncoder(cfg.modality_dims[name], cfg.cnn_channels,
                                                             cfg.kernel_size, cfg.dropout, causal=cfg.causal)
                                       for name in cfg.modality_order})
        self.fusion = nn.Linear(cfg.cnn_channels * len(cfg.modality_order), cfg.d_model)
        layer = nn.TransformerEncoderLayer(cfg.d_model, cfg.n_heads, cfg.ff_dim, cfg.dropout, batch_first=True)
        self.encoder = nn.TransformerEncoder(layer, cfg.n_layers, enable_nested_tensor=False)
        self.head = nn.Linear(cfg.d_model, cfg.n_classes)
        refine = MSTCNConfig(0, cfg.n_classes, refinement_layers=cfg.refinement_layers,
                             feature_maps=cfg.refinement_maps, dropout=cfg.refinement_dropout, causal=cfg.causal)
        self.refinements = nn.ModuleList(Refinement(refine) for _ in range(cfg.refinement_stages))
        self.register_buffer("positions", sinusoidal_positions(cfg.window, cfg.d_model), persistent=False)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        x, mask = look_ahead(x, mask, self.cfg.delay)
        b, _, t = x.shape
        w = self.cfg.window
        m = mask.unsqueeze(1).to(x.dtype)  # (B, T) -> (B, 1, T)
        parts = torch.split(x, [self.cfg.modality_dims[n] for n in self.cfg.modality_order], dim=1)
        encoded = [self.encoders[n](p, m) for n, p in zip(self.cfg.modality_order, parts)]  # each (B, K, T)
        h = self.fusion(torch.cat(encoded, dim=1).transpose(1, 2))  # (B, M*K, T) -> (B, T, M*K) -> (B, T, d)
        pad = (-t) % w
        h = F.pad(h, (0, 0, 0, pad))  # (B, T + pad, d)
        valid = F.pad(mask, (0, pad), value=False)  # (B, T + pad)
        n_windows = (t + pad) // w
        h = h.reshape(b * n_windows, w, -1) + self.positions  # (B, T', d) -> (B * nW, W, d)
        valid = valid.reshape(b * n_windows, w)  # (B * nW, W)
        empty = ~valid.any(dim=1)  # windows of pure padding would give NaN attention: unmask them
        # (W, W), True = a key after its query; made here, not a buffer: vmap (fold batching) stacks buffers
        future = torch.ones(w, w, dtype=torch.bool, device=x.device).triu(1) if self.cfg.causal else None
        h = self.encoder(h, mask=future,  # attends over W frames (causal: those at or before the query)
                         src_key_padding_mask=~(valid | empty.unsqueeze(1)))
        h = h.reshape(b, n_windows * w, -1)[:, :t]  # (B * nW, W, d) -> (B, T', d) -> (B, T, d)
        logits = self.head(h).transpose(1, 2) * m  # (B, T, C) -> (B, C, T)
        stages = [logits]
        for refinement in self.refinements:
            logits = refinement(F.softmax(logits, dim=1) * m, m)
            stages.append(logits)
        return shifted_back(torch.stack(stages), self.cfg.delay)  # (S, B, C, T)

    def loss(self, stages: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Per stage cross-entropy (+ the smoothing loss unless ``smoothing_weight`` is 0), summed;
        ``target`` (B, T) long, -1 = ignore. Plain variant: frame-wise cross-entropy alone."""
        return segmentation_loss(stages, target, mask, self.cfg.smoothing_weight, self.cfg.tau)

    @staticmethod
    def frame_logits(stages: torch.Tensor) -> torch.Tensor:
        return stages[-1]
