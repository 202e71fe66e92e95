"""Frame-by-frame inference (models/streaming.py): with random weights, the logits of every frame of a few
hundred equal the causal model's offline forward pass on the same frames, from a state whose size does
not grow with t; a model trained without --causal is refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from midas_cli.errors import ConfigError
from midas_cli.models.streaming import frame_stepper
from midas_cli.models.train import build_model

DIMS, CLASSES, FRAMES = {"emht": 5, "mtm": 3}, 4, 300
CONFIGS = {
    # dilations up to 2^8 = 256 and 2^6: the rings wrap within the 300 frames and the shortcut of a dilation
    # beyond the length so far is met early on
    "mstcn": {"pg_layers": 9, "refinement_stages": 2, "refinement_layers": 7, "feature_maps": 12},
    "transformer": {"cnn_channels": 8, "kernel_size": 5, "d_model": 16, "n_heads": 4, "ff_dim": 24, "window": 32,
                    "refinement_layers": 6, "refinement_maps": 8},
    "baseline-mlp": {"hidden": 6},
    "ensemble": {"members": ("mstcn", "transformer")},  # the members at their full size
}


def _model(name: str, causal: bool = True) -> torch.nn.Module:
    torch.manual_seed(3)
    model = build_model(name, DIMS, CLASSES, CONFIGS[name], causal=causal)[0].eval()
    with torch.no_grad():  # trained-looking weights: biases and norms away from their initial 0 / 1
        for p in model.parameters():
            p.add_(0.05 * torch.randn(p.shape))
    return model


@pytest.mark.parametrize("name", list(CONFIGS))
def test_stepping_equals_the_offline_causal_forward_pass(name):
    model = _model(name)
    x = np.random.default_rng(0).normal(size=(FRAMES, sum(DIMS.values())))
    with torch.no_grad():  # the offline pass in float64 (the stepper's precision): differences are rounding
        offline = model.double()(torch.from_numpy(x.T[None]), torch.ones(1, FRAMES, dtype=torch.bool))
    expected = model.frame_logits(offline)[0].numpy().T  # (C, T) -> (T, C)
    stepper = frame_stepper(model)
    sizes = []
    got = []
    for t in range(FRAMES):
        got.append(stepper.step(x[t]))
        sizes.append(stepper.state_floats())
    assert np.abs(np.array(got) - expected).max() < 1e-8
    assert len(set(sizes)) == 1  # the state does not grow with t
    if name != "baseline-mlp":
        assert sizes[0] > 0


def test_stepping_the_float32_model_agrees_to_float_rounding():
    model = _model("mstcn")
    x = np.random.default_rng(1).normal(size=(FRAMES, sum(DIMS.values()))).astype(np.float32)
    with torch.no_grad():
        offline = model(torch.from_numpy(x.T[None]), torch.ones(1, FRAMES, dtype=torch.bool))[-1, 0].numpy().T
    stepper = frame_stepper(model)
    stepped = np.array([stepper.step(frame) for frame in x])
    assert np.abs(stepped - offline).max() < 1e-4
    assert (stepped.argmax(axis=1) == offline.argmax(axis=1)).mean() > 0.99


@pytest.mark.parametrize("name", ["mstcn", "transformer"])
def test_a_model_trained_without_causal_is_refused(name):
    with pytest.raises(ConfigError, match="--causal"):
        frame_stepper(_model(name, causal=False))
