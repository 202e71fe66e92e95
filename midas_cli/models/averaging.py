"""The weights a run keeps with selection "average" (``train gestures --weights average``): the mean of
the network's weights after each epoch of the second half of training (epochs > epochs // 2), in place of
the last epoch's alone.

Why: with the shift augmentation (models/augment.py) and a constant learning rate, the last epoch's weights
are one draw from where Adam wanders near the end, and which draw a seed gets moves a fold's accuracy by
points. The mean of the weights the second half visits (weight averaging, as in stochastic weight
averaging) sits in the middle of that region. It costs one extra copy of the parameters and nothing at
test time: the run saves one network, as with "last", so live (`--causal`) models run it at the same cost.

Floating-point parameters and buffers are averaged (a running mean, float32 or wider); others (integer
counters) keep the last epoch's values. Every model here is free of batch statistics (MS-TCN++ has no
normalisation layers, the transformer layer norms only), so the averaged weights need no recomputed
buffers. Training itself does not change: the same batches, the same updates, the same random numbers.
"""

from __future__ import annotations

import torch


class WeightAverage:
    """Running mean of ``model``'s floating-point state over the epochs ``first`` .. the last."""

    def __init__(self, epochs: int) -> None:
        self.first = epochs // 2 + 1  # 20 epochs: 11..20; 10: 6..10; 1: 1
        self.count = 0
        self.mean: dict[str, torch.Tensor] = {}

    @torch.no_grad()
    def after_epoch(self, model: torch.nn.Module, epoch: int) -> None:
        """Fold in ``model``'s weights as they are at the end of ``epoch`` (earlier epochs: nothing)."""
        if epoch < self.first:
            return
        self.count += 1
        for name, value in model.state_dict().items():
            if not value.is_floating_point():
                continue
            if name not in self.mean:
                self.mean[name] = value.detach().to(torch.promote_types(value.dtype, torch.float32), copy=True)
            else:
                self.mean[name] += (value.detach() - self.mean[name]) / self.count

    @torch.no_grad()
    def apply(self, model: torch.nn.Module) -> None:
        """Set ``model``'s floating-point state to the mean (no epoch averaged: left as it is)."""
        if not self.count:
            return
        state = model.state_dict()
        for name, mean in self.mean.items():
            state[name].copy_(mean.to(state[name].dtype))
