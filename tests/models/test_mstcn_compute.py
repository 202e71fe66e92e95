"""MS-TCN++'s faster computation is the same network: a dual-dilated layer computed as one product over
its distinct taps equals its two dilated convolutions and 1x1 fusion as written (outputs and every
gradient), offline and causal, for dilations below and beyond the sequence; so does a dilated convolution
computed as one product over its shifted input; the uniform-draw dropout drops and scales as ``nn.Dropout`` does."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from midas_cli.models.mstcn import DilatedConv, DualDilatedLayer, Dropout


def _torch_conv(conv: DilatedConv, x: torch.Tensor) -> torch.Tensor:
    """The dilated convolution as torch computes it (zero padding: both sides, or the left only if causal)."""
    d = conv.dilation[0]
    if conv.causal:
        return F.conv1d(F.pad(x, (2 * d, 0)), conv.weight, conv.bias, dilation=d)
    return F.conv1d(x, conv.weight, conv.bias, padding=d, dilation=d)


def _as_written(layer: DualDilatedLayer, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The layer as published: each dilated convolution (torch's own), concatenated, fused by the 1x1."""
    fused = layer.fusion(torch.cat([_torch_conv(layer.conv_large, x), _torch_conv(layer.conv_small, x)], dim=1))
    return (x + F.relu(fused)) * mask


@pytest.mark.parametrize("causal", [False, True])
@pytest.mark.parametrize("dilation, length", [(1, 50), (8, 50), (20, 50), (30, 50), (50, 50), (512, 50), (2, 3)])
def test_dilated_convolution_is_torchs(causal, dilation, length):
    """Outputs and every gradient, with the taps that reach past the sequence (2d >= T > d) and all but one."""
    torch.manual_seed(dilation + length)
    conv = DilatedConv(6, dilation, causal)
    x = torch.randn(2, 6, length, requires_grad=True)
    ours, reference = conv(x), _torch_conv(conv, x)
    assert ours.shape == reference.shape
    assert torch.allclose(ours, reference, atol=1e-5, rtol=1e-5)
    params = [x, conv.weight, conv.bias]
    probe = torch.randn_like(ours)
    for a, b in zip(torch.autograd.grad((ours * probe).sum(), params), torch.autograd.grad((reference * probe).sum(), params)):
        assert torch.allclose(a, b, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("causal", [False, True])
@pytest.mark.parametrize("small, large, length", [(1, 1024, 300), (4, 256, 300), (32, 32, 300),
                                                  (512, 2, 300), (16, 64, 40), (2, 8, 9)])
def test_dual_dilated_layer_is_its_convolutions_and_fusion(causal, small, large, length):
    torch.manual_seed(small + large + length)
    layer = DualDilatedLayer(8, small, large, 0.0, causal).eval()
    x = torch.randn(3, 8, length, requires_grad=True)
    mask = torch.ones(3, 1, length)
    mask[1, :, length // 2:] = 0.0  # a shorter sequence in the batch
    ours = layer(x, mask)
    reference = _as_written(layer, x, mask)
    assert torch.allclose(ours, reference, atol=1e-5, rtol=1e-5)
    params = [x] + list(layer.parameters())
    probe = torch.randn_like(ours)
    g_ours = torch.autograd.grad((ours * probe).sum(), params)
    g_ref = torch.autograd.grad((reference * probe).sum(), params)
    for a, b in zip(g_ours, g_ref):
        assert torch.allclose(a, b, atol=1e-4, rtol=1e-4)


def test_causal_dual_layer_output_never_depends_on_later_frames():
    torch.manual_seed(1)
    layer = DualDilatedLayer(4, 2, 16, 0.0, causal=True).eval()
    x = torch.randn(1, 4, 50)
    changed = x.clone()
    changed[..., 30:] += 5.0
    mask = torch.ones(1, 1, 50)
    a, b = layer(x, mask), layer(changed, mask)
    assert torch.equal(a[..., :30], b[..., :30])
    assert not torch.allclose(a[..., 30:], b[..., 30:])


def test_dropout_keeps_and_scales_like_torch_dropout():
    torch.manual_seed(0)
    drop = Dropout(0.5)
    x = torch.ones(200_000)
    out = drop(x)
    kept = out != 0
    assert set(torch.unique(out).tolist()) == {0.0, 2.0}  # kept values scaled by 1 / (1 - p)
    assert abs(kept.float().mean().item() - 0.5) < 0.01
    assert abs(out.mean().item() - 1.0) < 0.02  # expectation preserved
    assert not torch.equal(drop(x), out)  # a new mask per call
    torch.manual_seed(0)
    assert torch.equal(Dropout(0.5)(x), out)  # seeded: reproducible
    assert abs((Dropout(0.2)(x) != 0).float().mean().item() - 0.8) < 0.01
    drop.eval()
    assert torch.equal(drop(x), x)
    assert torch.equal(Dropout(0.0)(x), x)
    assert torch.equal(Dropout(1.0)(x), torch.zeros_like(x))
    assert Dropout(0.5)(torch.ones(8, dtype=torch.float16)).dtype == torch.float16  # mixed precision: no upcast


def test_dropout_gradient_flows_through_kept_elements_only():
    torch.manual_seed(3)
    x = torch.randn(1000, requires_grad=True)
    out = Dropout(0.5)(x)
    out.sum().backward()
    assert torch.equal(x.grad, (out != 0).float() * 2.0)
