"""The MS-TCN++ reference benchmark compares like with like (no timing is asserted): the reference
network written from the paper has midas's parameter count, gives midas's outputs with midas's weights,
and its loss equals midas's at batch 1."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import bench_mstcn_reference as ref_bench  # noqa: E402

from midas_cli.models.mstcn import MSTCNConfig  # noqa: E402
from midas_cli.models.train import build_model  # noqa: E402


def _pair() -> tuple[torch.nn.Module, ref_bench.ReferenceMSTCN, MSTCNConfig]:
    torch.manual_seed(0)
    midas, cfg = build_model("mstcn", {"columns": ref_bench.COLUMNS}, ref_bench.CLASSES, {})
    c = MSTCNConfig(**cfg)
    ref = ref_bench.ReferenceMSTCN(c.pg_layers, c.refinement_stages, c.refinement_layers, c.feature_maps,
                                   c.in_features, c.n_classes, c.dropout)
    return midas, ref, c


def test_reference_is_midas_network_and_loss() -> None:
    midas, ref, cfg = _pair()
    xs, ys = ref_bench.synthetic_arrays(1)
    x, y = xs[0][:400], ys[0][:400]
    check = ref_bench.check_same_network(midas, ref, x)  # raises unless counts and outputs agree
    assert check["parameters_midas"] == check["parameters_reference"]
    inputs = torch.from_numpy(np.ascontiguousarray(x.T))[None]
    target = torch.from_numpy(y)[None]
    with torch.no_grad():
        stages = midas(inputs, torch.ones(1, len(y), dtype=torch.bool))
        ours = midas.loss(stages, target, torch.ones(1, len(y), dtype=torch.bool))
        theirs = ref_bench.reference_loss(stages, target, cfg.smoothing_weight, cfg.tau)
    assert torch.allclose(ours, theirs, rtol=1e-5, atol=1e-6)


def test_synthetic_arrays_are_jigsaws_sized_and_seeded() -> None:
    xs, ys = ref_bench.synthetic_arrays(3)
    again, _ = ref_bench.synthetic_arrays(3)
    assert all(x.shape == (len(y), ref_bench.COLUMNS) and x.dtype == np.float32 for x, y in zip(xs, ys))
    assert all(ref_bench.MIN_FRAMES <= len(y) <= ref_bench.MAX_FRAMES for y in ys)
    assert all(np.array_equal(a, b) for a, b in zip(xs, again))
