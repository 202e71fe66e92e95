"""The folds of a cross-validation trained together: K models of one architecture in one process, as
one stacked computation (``torch.func.stack_module_state`` + ``functional_call`` + ``torch.vmap`` over
the model dimension; dropout draws differ per model).

Why: a fold of MS-TCN++ at batch size 1 is hundreds of small kernels a step; on one GPU, K processes
(``--jobs K``) time-slice the device. Batched, each step launches those kernels once for all K folds.

Every fold trains exactly as its own run would (models/train.py ``fit``): the same initial weights
(``torch.manual_seed(seed)`` before building each model), the same batch order (its own
``default_rng(seed)``), its own Adam state and step count, its own input shifts (``--augment-shift``,
models/augment.py). At each step every fold takes its next
batch; the batches are padded to a common length (the models mask every padding frame, so a real
frame's output does not change) and stacked. A fold whose epoch has fewer batches than another's has
no batch at the last steps: its loss is left out and its step is masked (weights, Adam moments and
step count unchanged). Selection ("last", "best-val" or "average") and the run folders (``fold-<k>/``) are per
fold, as ``train_run`` writes them. On CUDA the forward pass runs in autocast float16 with a loss
scale per fold (GradScaler's rule: a step with inf/nan gradients is skipped and halves that fold's
scale; 2000 good steps double it). Bit-equality with separate runs is not kept where dropout is on
(vmap draws the dropout masks from one generator); with dropout 0 weights agree up to float rounding.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from torch.func import functional_call, stack_module_state

from midas_cli.errors import ConfigError
from midas_cli.models.data import DatasetConfig, build_dataset
from midas_cli.models.run_files import new_run_dir
from midas_cli.models.augment import ColumnShift
from midas_cli.models.averaging import WeightAverage
from midas_cli.models.ensemble import Ensemble, each_member, member_records
from midas_cli.models.predict import frame_accuracy
from midas_cli.models.sequences import Sequences, epoch_inputs, padded_batches
from midas_cli.models.train import ProgressFn, TrainConfig, finish_run, prepare_fold, seeded_model, torch_device

log = logging.getLogger(__name__)

MODES = ("auto", "on", "off")
BETAS, EPS = (0.9, 0.999), 1e-8  # torch.optim.Adam's defaults, as fit() uses them
SCALE_INIT, SCALE_GROWTH_STEPS = 2.0 ** 16, 2000  # torch.amp.GradScaler's defaults


def enabled(mode: str, device: str, folds: int) -> bool:
    """Whether ``mode`` (auto, on, off) trains ``folds`` folds batched on ``device``: auto = on CUDA only
    (on the CPU the stacked step is slower per epoch than the folds one after another)."""
    if mode not in MODES:
        raise ConfigError(f"--fold-batch must be one of {', '.join(MODES)}, got {mode!r}")
    return folds > 1 and (mode == "on" or (mode == "auto" and device == "cuda"))


def train_folds(sessions: Sequence[Path], data_config: DatasetConfig, config: TrainConfig,
                run_dirs: dict[int, Path], progress: ProgressFn | None = None) -> None:
    """Train fold k of ``config`` into ``run_dirs[k]`` for every k, batched; each folder as ``train_run``
    writes it."""
    config = config.resolved()
    device = torch_device(config.device)
    dataset = build_dataset(sessions, data_config)
    folds = sorted(run_dirs)
    for k in folds:
        new_run_dir(run_dirs[k])
    configs = [replace(config, fold=k) for k in folds]
    prepared = [prepare_fold(dataset, c) for c in configs]
    built = [seeded_model(dataset, c) for c in configs]
    models = [model.to(device) for model, _ in built]
    histories = fit_stacked(models, [p.parts["train"] for p in prepared], [p.parts["val"] for p in prepared],
                            config, device, progress, [p.augment for p in prepared])
    for k, c, fold, model, (_, model_cfg), history in zip(folds, configs, prepared, models, built, histories):
        finish_run(run_dirs[k], dataset, fold, c, model, model_cfg, history, device)


@dataclass
class StepState:
    """Per-fold optimiser state: Adam's moments over the flattened parameters, step counts, loss scales."""

    m: torch.Tensor  # (P_total,) every parameter's K copies, flattened one after another
    v: torch.Tensor
    steps: torch.Tensor  # (K,) Adam steps taken
    scale: torch.Tensor  # (K,) loss scale (1 without mixed precision)
    good: torch.Tensor  # (K,) steps since the scale last changed
    owner: torch.Tensor  # (P_total,) long: the fold of each flat entry
    mixed: bool  # CUDA autocast: scaled losses, steps with inf/nan gradients skipped


def fit_stacked(models: list[torch.nn.Module], trains: list[Sequences], vals: list[Sequences], config: TrainConfig,
                device: torch.device, progress: ProgressFn | None = None,
                augments: Sequence[ColumnShift | None] | None = None) -> list[list[dict]]:
    """``fit`` for K models of one architecture at once (see the module text); the models get their
    trained (or best-validation) weights; ``augments``: each fold's (``fit``'s ``augment``). Returns each
    fold's history. Ensembles: each member's K copies stacked in turn (ensemble.py ``each_member``)."""
    config = config.resolved()
    if isinstance(models[0], Ensemble):
        histories: list[list[dict]] = [[] for _ in models]
        for i, member_config, member_progress in each_member(config, models[0].cfg.members, progress):
            fitted = fit_stacked([m.members[i] for m in models], trains, vals, member_config, device, member_progress,
                                 augments)
            for history, records in zip(histories, fitted):
                history += member_records(i, member_config, records)
        return histories
    step = StackedStep(models, device)
    rngs = [np.random.default_rng(config.seed) for _ in models]
    augments = list(augments) if augments is not None else [None] * len(models)
    histories = [[] for _ in models]
    best: list[tuple[float, dict | None]] = [(-1.0, None) for _ in models]
    averages = [WeightAverage(config.epochs) for _ in models] if config.selection == "average" else []
    for epoch in range(1, config.epochs + 1):
        batches = [list(padded_batches(epoch_inputs(t, a), r.permutation(len(t.x)), config.batch_size))
                   for t, r, a in zip(trains, rngs, augments)]
        loss_sum = torch.zeros(len(models), device=device)
        for i in range(max(map(len, batches))):
            active = torch.tensor([i < len(b) for b in batches], device=device)
            x, y, mask = _stack([b[i] if i < len(b) else b[0] for b in batches], device)
            loss_sum += step(x, y, mask, active, config).float()
        _copy_into(models, step.params)
        for k, model in enumerate(models):
            val_acc = frame_accuracy(model, vals[k], device) if vals[k].units else None
            histories[k].append({"epoch": epoch, "loss": float(loss_sum[k]) / len(batches[k]), "val_accuracy": val_acc})
            if config.selection == "best-val" and val_acc is not None and val_acc > best[k][0]:
                best[k] = (val_acc, {n: v.detach().clone() for n, v in model.state_dict().items()})
        for model, average in zip(models, averages):
            average.after_epoch(model, epoch)
        if progress:
            progress(epoch, config.epochs, histories[0][-1])
    for model, (_, weights) in zip(models, best):
        if weights is not None:
            model.load_state_dict(weights)
    for model, average in zip(models, averages):
        average.apply(model)
    return histories


class StackedStep:
    """K models of one architecture as one stacked computation (``stack_module_state``, the forward and
    loss under vmap, ``_stacked_loss``) with each fold's Adam state (``StepState``); a call is one training
    step of every fold, ``fit_stacked``'s (``benchmarks/bench_fold_batch.py`` measures this same step)."""

    def __init__(self, models: Sequence[torch.nn.Module], device: torch.device) -> None:
        self.params, self.buffers = stack_module_state(list(models))  # type: ignore[arg-type]
        for p in self.params.values():
            p.requires_grad_(True)
        mixed = device.type == "cuda"
        self.state = new_state(list(self.params.values()), len(models), device, mixed)
        self._loss = _stacked_loss(models[0], mixed, device)

    def backward(self, x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
        """The K losses of a stacked batch (``_stack``) and their gradients, scaled by each fold's loss scale;
        a fold not ``active`` (K,) bool has no batch this step: its loss is 0 and gives no gradient."""
        losses = self._loss(self.params, self.buffers, x, y, mask)
        losses = torch.where(active, losses, torch.zeros_like(losses))
        (losses * self.state.scale).sum().backward()
        return losses.detach()

    def __call__(self, x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor, active: torch.Tensor,
                 config: TrainConfig) -> torch.Tensor:
        """``backward``, then the Adam step of the ``active`` folds; the K losses."""
        losses = self.backward(x, y, mask, active)
        adam_step(list(self.params.values()), self.state, active, config)
        return losses


def _stacked_loss(base: torch.nn.Module, mixed: bool, device: torch.device) -> Callable[..., torch.Tensor]:
    """(params, buffers, x, y, mask), each with a leading fold dimension -> the K training losses (K,)."""

    def one(params: dict, buffers: dict, x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        with torch.autocast(device_type=device.type, dtype=torch.float16, enabled=mixed):
            stages = functional_call(base, (params, buffers), (x, mask))
            return base.loss(stages, y, mask)  # type: ignore[operator]

    batched = torch.vmap(one, randomness="different")

    def run(params: dict, buffers: dict, x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        base.train()
        return batched(params, buffers, x, y, mask)

    return run


def _stack(batches: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]],
           device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-fold padded batches -> x (K, B, D, T), y (K, B, T) (-1 on padding), mask (K, B, T); rows and
    frames a fold lacks are padding."""
    b = max(x.shape[0] for x, _, _ in batches)
    t = max(x.shape[2] for x, _, _ in batches)
    xs = torch.zeros(len(batches), b, batches[0][0].shape[1], t)
    ys = torch.full((len(batches), b, t), -1, dtype=torch.int64)
    masks = torch.zeros(len(batches), b, t, dtype=torch.bool)
    for k, (x, y, mask) in enumerate(batches):
        xs[k, :x.shape[0], :, :x.shape[2]] = x
        ys[k, :y.shape[0], :y.shape[1]] = y
        masks[k, :mask.shape[0], :mask.shape[1]] = mask
    return xs.to(device), ys.to(device), masks.to(device)


def new_state(params: list[torch.Tensor], k: int, device: torch.device, mixed: bool) -> StepState:
    """Zero moments and step counts for ``k`` folds of the stacked ``params``; GradScaler's first scale if ``mixed``."""
    sizes = [p[0].numel() for p in params]
    owner = torch.cat([torch.arange(k, device=device).repeat_interleave(n) for n in sizes])
    zeros = torch.zeros(owner.shape[0], device=device)
    return StepState(zeros, zeros.clone(), torch.zeros(k, device=device),
                     torch.full((k,), SCALE_INIT if mixed else 1.0, device=device),
                     torch.zeros(k, device=device), owner, mixed)


@torch.no_grad()
def adam_step(params: list[torch.Tensor], state: StepState, active: torch.Tensor, config: TrainConfig) -> None:
    """One Adam step (torch.optim.Adam's update, L2 weight decay) of the folds in ``active`` (K,) bool;
    the others keep weights, moments and step count. Gradients are unscaled per fold; a fold whose
    gradients are not finite skips the step and halves its scale (mixed precision)."""
    grad = torch.cat([p.grad.reshape(-1) for p in params]) / state.scale[state.owner]  # type: ignore[union-attr]
    bad = torch.zeros_like(active)
    if state.mixed:
        bad = torch.zeros_like(state.scale).index_add_(0, state.owner, (~torch.isfinite(grad)).float()) > 0
        grad = torch.nan_to_num(grad)
        active = active & ~bad
    if config.weight_decay:
        grad = grad + config.weight_decay * torch.cat([p.reshape(-1) for p in params])
    state.steps += active.float()
    on = active[state.owner]
    beta1, beta2 = BETAS
    state.m = torch.where(on, state.m.lerp(grad, 1 - beta1), state.m)
    state.v = torch.where(on, state.v * beta2 + (1 - beta2) * grad * grad, state.v)
    t = state.steps.clamp(min=1)
    step_size = (config.lr / (1 - beta1 ** t)) * active.float()  # (K,): 0 for a fold that does not step
    denom = state.v.sqrt() / torch.sqrt(1 - beta2 ** t)[state.owner] + EPS
    update = (-step_size[state.owner] * state.m / denom).split([p.numel() for p in params])
    torch._foreach_add_(params, [u.view_as(p) for u, p in zip(update, params)])
    for p in params:
        p.grad = None
    if state.mixed:
        _update_scale(state, bad)


def _update_scale(state: StepState, bad: torch.Tensor) -> None:
    """GradScaler's rule per fold: inf/nan halves the scale, SCALE_GROWTH_STEPS good steps double it."""
    state.good = torch.where(bad, torch.zeros_like(state.good), state.good + 1)
    grow = state.good >= SCALE_GROWTH_STEPS
    state.scale = torch.where(bad, state.scale * 0.5, torch.where(grow, state.scale * 2.0, state.scale))
    state.good = torch.where(grow, torch.zeros_like(state.good), state.good)


@torch.no_grad()
def _copy_into(models: list[torch.nn.Module], params: dict[str, torch.Tensor]) -> None:
    """Each model's parameters set to its slice of the stacked ones (for evaluation and saving)."""
    for k, model in enumerate(models):
        for name, p in model.named_parameters():
            p.copy_(params[name][k])

