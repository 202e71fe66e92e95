"""Causal gesture models run one frame at a time: frame t's logits from frame t's features and a state
of fixed size (issue 28: live recognition in constant time and memory per frame, no window re-run).

Every causal layer keeps what its future outputs still need: a dilated 3-tap convolution (taps t - 2d,
t - d, t) a ring buffer of its last 2d + 1 inputs, a k-tap encoder convolution its last k inputs, a
transformer layer the keys and values of the current attention window (reset at each window start,
so a frame attends to at most ``window`` frames). A ring starts as zeros: the zero padding the offline
forward pass puts before the first frame. The arithmetic is the network's own, in float64 numpy with
the trained weights (eval mode: dropout off), so the logits equal the offline causal forward pass on the
same frames up to float rounding (tests/models/test_streaming.py). A delayed model (``cfg.delay`` frames,
``train gestures --delay``) steps the same way: its step at frame t gives frame t - delay's logits
(``analysis/live_gestures.py`` keeps the frames waiting for theirs and flushes them with zero frames).

``frame_stepper(model)`` builds the stepper of a trained network (MS-TCN++, the transformer, the
per-frame baselines, an ensemble of them); a sequence model trained without ``causal`` is refused (it would need frames
after t).
"""

from __future__ import annotations

import math
from typing import Callable, Protocol

import numpy as np
import torch
from torch import nn

from midas_cli.errors import ConfigError
from midas_cli.models.baseline import FrameBaseline
from midas_cli.models.ensemble import TINY, Ensemble
from midas_cli.models.mstcn import MSTCN, DualDilatedLayer, PredictionGeneration, Refinement
from midas_cli.models.transformer import GestureTransformer


class FrameStepper(Protocol):
    """One frame in, that frame's class logits out."""

    def step(self, x: np.ndarray) -> np.ndarray:
        """``x`` (D,) the frame's (normalised) features -> (C,) logits of the last stage."""
        ...

    def state_floats(self) -> int:
        """How many numbers the state holds (fixed once built)."""
        ...


def _array(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().cpu().double().numpy()


def _softmax(logits: np.ndarray) -> np.ndarray:
    e = np.exp(logits - logits.max())
    return e / e.sum()


class Ring:
    """The last ``length`` vectors of size ``dim`` pushed, zeros before the first."""

    def __init__(self, length: int, dim: int) -> None:
        self.values = np.zeros((length, dim))
        self.pos = -1

    def push(self, v: np.ndarray) -> None:
        self.pos = (self.pos + 1) % len(self.values)
        self.values[self.pos] = v


class StepConv:
    """A causal convolution (``DilatedConv`` or a left-padded encoder ``nn.Conv1d``) over a ring of its
    inputs: y_t = b + sum_j W[:, :, j] @ x_(t - (k - 1 - j) d)."""

    def __init__(self, conv: nn.Conv1d) -> None:
        out, width, taps = conv.weight.shape
        self.weight = _array(conv.weight).transpose(0, 2, 1).reshape(out, taps * width)  # (out, in, k) -> (out, k * in)
        self.bias = _array(conv.bias) if conv.bias is not None else np.zeros(out)
        dilation = int(conv.dilation[0])
        self.lags = (taps - 1 - np.arange(taps)) * dilation  # tap j reads the input (k - 1 - j) d frames back
        self.ring = Ring((taps - 1) * dilation + 1, width)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        self.ring.push(x)
        inputs = self.ring.values[(self.ring.pos - self.lags) % len(self.ring.values)]  # (k, in), oldest first
        return self.weight @ inputs.reshape(-1) + self.bias


def _linear(layer: nn.Module) -> Callable[[np.ndarray], np.ndarray]:
    """An ``nn.Linear`` or 1x1 ``nn.Conv1d`` as a function of one frame's vector."""
    return _linear_of(layer.weight, layer.bias)


def _linear_of(weight: torch.Tensor, bias: torch.Tensor) -> Callable[[np.ndarray], np.ndarray]:
    w = _array(weight).reshape(weight.shape[0], -1)  # (out, in[, 1]) -> (out, in)
    b = _array(bias)
    return lambda v: w @ v + b


def _layer_norm(x: np.ndarray, weight: np.ndarray, bias: np.ndarray, eps: float) -> np.ndarray:
    centred = x - x.mean()
    return centred / np.sqrt((centred ** 2).mean() + eps) * weight + bias


class StepGeneration:
    """MS-TCN++'s prediction-generation stage, one frame at a time."""

    def __init__(self, stage: PredictionGeneration) -> None:
        self.conv_in, self.conv_out = _linear(stage.conv_in), _linear(stage.conv_out)
        self.layers = [(StepConv(layer.conv_large), StepConv(layer.conv_small), _linear(layer.fusion))
                       for layer in stage.layers if isinstance(layer, DualDilatedLayer)]

    def __call__(self, x: np.ndarray) -> np.ndarray:
        h = self.conv_in(x)
        for large, small, fusion in self.layers:
            h = h + np.maximum(fusion(np.concatenate([large(h), small(h)])), 0.0)
        return self.conv_out(h)

    def state_floats(self) -> int:
        return sum(c.ring.values.size for large, small, _ in self.layers for c in (large, small))


class StepRefinement:
    """An MS-TCN++ refinement stage (on the previous stage's softmax), one frame at a time."""

    def __init__(self, stage: Refinement) -> None:
        self.conv_in, self.conv_out = _linear(stage.conv_in), _linear(stage.conv_out)
        self.layers = [(StepConv(layer.conv_dilated), _linear(layer.conv_1x1)) for layer in stage.layers]

    def __call__(self, logits: np.ndarray) -> np.ndarray:
        h = self.conv_in(_softmax(logits))
        for conv, pointwise in self.layers:
            h = h + pointwise(np.maximum(conv(h), 0.0))
        return self.conv_out(h)

    def state_floats(self) -> int:
        return sum(conv.ring.values.size for conv, _ in self.layers)


class StepMSTCN:
    """Causal MS-TCN++: the generation stage then each refinement stage, per frame."""

    def __init__(self, model: MSTCN) -> None:
        self.generation = StepGeneration(model.generation)
        self.refinements = [StepRefinement(r) for r in model.refinements]

    def step(self, x: np.ndarray) -> np.ndarray:
        logits = self.generation(np.asarray(x, dtype=np.float64))
        for refinement in self.refinements:
            logits = refinement(logits)
        return logits

    def state_floats(self) -> int:
        return self.generation.state_floats() + sum(r.state_floats() for r in self.refinements)


class StepAttentionLayer:
    """A post-norm ``nn.TransformerEncoderLayer`` (ReLU) with causal attention inside a window: the keys
    and values of the window's frames so far are kept (``window`` x d each)."""

    def __init__(self, layer: nn.TransformerEncoderLayer, window: int) -> None:
        if layer.norm_first or layer.activation_relu_or_gelu != 1:
            raise ConfigError("only post-norm ReLU transformer layers can run one frame at a time")
        attention = layer.self_attn
        self.heads = attention.num_heads
        self.in_proj, self.out_proj = _linear_of(attention.in_proj_weight, attention.in_proj_bias), _linear(attention.out_proj)
        self.linear1, self.linear2 = _linear(layer.linear1), _linear(layer.linear2)
        self.norms = [(_array(n.weight), _array(n.bias), n.eps) for n in (layer.norm1, layer.norm2)]
        d = attention.embed_dim
        self.keys, self.values = np.zeros((window, d)), np.zeros((window, d))

    def __call__(self, x: np.ndarray, position: int) -> np.ndarray:
        """``x`` (d,) the frame at ``position`` of its window (0 starts a new window)."""
        d = len(x)
        q, k, v = np.split(self.in_proj(x), 3)
        self.keys[position], self.values[position] = k, v
        per_head = d // self.heads
        q = q.reshape(self.heads, per_head)  # (d,) -> (H, d/H)
        keys = self.keys[: position + 1].reshape(position + 1, self.heads, per_head)  # (p+1, d) -> (p+1, H, d/H)
        values = self.values[: position + 1].reshape(position + 1, self.heads, per_head)
        scores = np.einsum("hc,phc->hp", q, keys) / math.sqrt(per_head)  # (H, p+1)
        weights = np.exp(scores - scores.max(axis=1, keepdims=True))
        weights /= weights.sum(axis=1, keepdims=True)
        attended = np.einsum("hp,phc->hc", weights, values).reshape(d)  # (H, d/H) -> (d,)
        x = _layer_norm(x + self.out_proj(attended), *self.norms[0])
        return _layer_norm(x + self.linear2(np.maximum(self.linear1(x), 0.0)), *self.norms[1])

    def state_floats(self) -> int:
        return self.keys.size + self.values.size


class StepTransformer:
    """The causal transformer: per modality its causal CNN encoder, fusion, the window position code,
    the attention layers over the window so far, the head, then the causal refinement stages."""

    def __init__(self, model: GestureTransformer) -> None:
        cfg = model.cfg
        self.window, self.t = cfg.window, 0
        self.splits = np.cumsum([cfg.modality_dims[n] for n in cfg.modality_order])[:-1]
        self.encoders = [[StepConv(conv) for conv in model.encoders[n].convs] for n in cfg.modality_order]
        self.fusion, self.head = _linear(model.fusion), _linear(model.head)
        self.positions = _array(model.positions)  # (W, d)
        self.layers = [StepAttentionLayer(layer, cfg.window) for layer in model.encoder.layers]
        self.refinements = [StepRefinement(r) for r in model.refinements]

    def step(self, x: np.ndarray) -> np.ndarray:
        encoded = []
        for convs, part in zip(self.encoders, np.split(np.asarray(x, dtype=np.float64), self.splits)):
            for conv in convs:
                part = np.maximum(conv(part), 0.0)
            encoded.append(part)
        position = self.t % self.window
        self.t += 1
        h = self.fusion(np.concatenate(encoded)) + self.positions[position]
        for layer in self.layers:
            h = layer(h, position)
        logits = self.head(h)
        for refinement in self.refinements:
            logits = refinement(logits)
        return logits

    def state_floats(self) -> int:
        return (sum(c.ring.values.size for convs in self.encoders for c in convs)
                + sum(layer.state_floats() for layer in self.layers) + sum(r.state_floats() for r in self.refinements))


class StepBaseline:
    """A per-frame baseline: no state."""

    def __init__(self, model: FrameBaseline) -> None:
        layers = [m for m in model.net.modules() if isinstance(m, nn.Conv1d)]
        self.layers = [_linear(m) for m in layers]

    def step(self, x: np.ndarray) -> np.ndarray:
        h = np.asarray(x, dtype=np.float64)
        for i, layer in enumerate(self.layers):
            h = layer(h) if i == 0 else layer(np.maximum(h, 0.0))  # ReLU between the MLP's layers
        return h

    def state_floats(self) -> int:
        return 0


class StepEnsemble:
    """An ensemble's members stepped side by side; the logits are the log of their mean probabilities, as
    ``Ensemble.forward`` gives them (the members share the ensemble's delay, so their steps label one frame)."""

    def __init__(self, model: Ensemble) -> None:
        self.members = [frame_stepper(member) for member in model.members]

    def step(self, x: np.ndarray) -> np.ndarray:
        probs = np.mean([_softmax(member.step(x)) for member in self.members], axis=0)
        return np.log(np.maximum(probs, TINY))

    def state_floats(self) -> int:
        return sum(member.state_floats() for member in self.members)


def frame_stepper(model: nn.Module) -> FrameStepper:
    """The stepper of a trained causal network; ConfigError for one that is not causal."""
    if isinstance(model, FrameBaseline):
        return StepBaseline(model)
    if not getattr(model.cfg, "causal", False):
        raise ConfigError(f"the {type(model).__name__} model was not trained with --causal: it needs frames after "
                          "t and cannot run one frame at a time")
    if isinstance(model, Ensemble):
        return StepEnsemble(model)
    if isinstance(model, MSTCN):
        return StepMSTCN(model)
    if isinstance(model, GestureTransformer):
        return StepTransformer(model)
    raise ConfigError(f"no frame-by-frame version of {type(model).__name__}")

