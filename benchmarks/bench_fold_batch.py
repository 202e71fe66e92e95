"""The folds of a cross-validation batched in one process, measured without a GPU: per training step of
each ensemble member at its recipe, the operators torch dispatches (what a GPU would launch as kernels)
and the arithmetic, for one fold trained alone and for K folds batched (issue 27: "if no GPU is lent, give
the GPU-free evidence of the design: one process, batched folds").

Why operators: MS-TCN++ at batch 1 is hundreds of small operators a step. On a GPU each is a kernel launch
of a few microseconds whatever its size, so K processes (``--jobs K``) issue K streams of them and
time-slice the device, while batched folds (``models/fold_batch.py``: K copies under ``torch.vmap``) issue
one stream whose operators are K times larger. What this measures, on the CPU, exactly as the code runs:

* one fold alone: ``fit``'s step (forward, loss, backward, fused Adam; ``models/train.py``);
* K folds batched, K = 1, 2, 4, 8: ``fit_stacked``'s step itself (``fold_batch.StackedStep``: vmap'd
  forward and loss, backward, the stacked Adam step), counted with a ``TorchDispatchMode`` below vmap (after batching rules: an operator
  with no batching rule runs once per fold and shows as growth with K). Views (``is_view``: no kernel)
  are counted apart. The second step is counted (the first creates Adam's state).
* FLOPs of one fold's step (``torch.utils.flop_counter``: matrix products and convolutions; K folds do K
  times that. Not counted batched: the counter takes a grouped convolution's weight gradient as if it
  were ungrouped, K times too many, which the step's time does not show), and the CPU seconds of a step
  (one thread; the machine may be shared: the load is recorded).
* The host's cost an operator: the CPU seconds of a forward and backward pass on trials of
  ``--floor-frames`` frames, one fold (alone, and batched with K = 1), where the arithmetic is next to
  nothing and what is left is issuing the operators (Python, autograd, vmap), divided by that pass's
  operators (the least of 10 x ``--reps`` passes). The optimiser's update is left out: its operators are
  few, but on a CPU its arithmetic over every parameter is real work that a GPU does in a fraction of a
  millisecond. A GPU computes asynchronously, so steps x operators x this cost is about the least a run
  takes from a CPU like this one.

Shapes: the Suturing-sized LOUO of ``bench_train.py --louo-all`` (38 trials of ~1,085 frames at the
model's 10 Hz, 40 inputs: mtm + psm pos, vel, angvel, grasper; 8 folds; ~33 training trials a fold).
Trials are given one length (the padding a batch of uneven folds adds is not counted). On CUDA the forward
runs under autocast (float16 casts add operators to both sides alike); the CPU stays float32.

    .venv/bin/python benchmarks/bench_fold_batch.py [--frames 1085] [--ks 1,2,4,8] [--quick]   # -> results/fold_batch.json
    python3 benchmarks/bench_fold_batch.py --device cuda   # on a GPU (gpu_check.sh) -> results/fold_batch-cuda.json
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import Counter
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import FlopCounterMode

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load_average, machine_info, write_result  # noqa: E402

from midas_cli.models import fold_batch  # noqa: E402
from midas_cli.models.ensemble import MEMBERS  # noqa: E402
from midas_cli.models.train import RECIPES, TrainConfig, build_model  # noqa: E402

DIMS = {"mtm": 20, "psm": 20}  # the CLI's robot inputs: pos 3, vel 3, angvel 3, grasper 1, per side
CLASSES = 10  # JIGSAWS Suturing's gestures
TRAIN_TRIALS = 33  # 38 trials, 8 users: a LOUO fold trains on ~33


class OperatorCount(TorchDispatchMode):
    """Every aten operator dispatched while active: kernels (not views) and views apart."""

    def __init__(self) -> None:
        super().__init__()
        self.kernels: Counter[str] = Counter()
        self.views = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001
        if func.is_view:
            self.views += 1
        else:
            self.kernels[str(func.overloadpacket)] += 1
        return func(*args, **(kwargs or {}))


def _model(name: str, device: torch.device) -> torch.nn.Module:
    torch.manual_seed(0)
    return build_model(name, DIMS, CLASSES, {})[0].to(device)


def _batch(k: int | None, batch: int, frames: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """x (B, D, T), y, mask; with a leading fold dimension K when ``k`` is given."""
    lead = (k,) if k else ()
    x = torch.randn(*lead, batch, sum(DIMS.values()), frames)
    y = torch.randint(0, CLASSES, (*lead, batch, frames))
    return x.to(device), y.to(device), torch.ones(*lead, batch, frames, dtype=torch.bool, device=device)


def _alone(name: str, config: TrainConfig, frames: int, device: torch.device, update: bool = True):  # noqa: ANN202
    """fit's training step for one fold (models/train.py, its loop's body), as a callable; without the
    optimiser's update if not ``update``."""
    model = _model(name, device)
    optimiser = torch.optim.Adam(model.parameters(), lr=config.lr, weight_decay=config.weight_decay, fused=True)
    x, y, mask = _batch(None, config.batch_size, frames, device)
    mixed = device.type == "cuda"  # as fit: autocast float16 and a loss scale on CUDA
    scaler = torch.amp.GradScaler("cuda", enabled=mixed)

    def step() -> None:
        model.train()
        with torch.autocast(device_type=device.type, dtype=torch.float16, enabled=mixed):
            loss = model.loss(model(x, mask), y, mask)
        optimiser.zero_grad()
        scaler.scale(loss).backward()
        if update:
            scaler.step(optimiser)
            scaler.update()

    return step


def _batched(name: str, config: TrainConfig, frames: int, k: int, device: torch.device, update: bool = True):  # noqa: ANN202
    """fit_stacked's training step for ``k`` folds (``fold_batch.StackedStep``), as a callable; without
    the Adam step (the gradients dropped) if not ``update``."""
    step = fold_batch.StackedStep([_model(name, device) for _ in range(k)], device)
    x, y, mask = _batch(k, config.batch_size, frames, device)
    active = torch.ones(k, dtype=torch.bool, device=device)

    def run() -> None:
        if update:
            step(x, y, mask, active, config)
            return
        step.backward(x, y, mask, active)
        for p in step.params.values():
            p.grad = None

    return run


def _clock() -> float:
    """The process's CPU seconds; with CUDA in use, the wall clock once the device has finished its work."""
    if torch.cuda.is_initialized():
        torch.cuda.synchronize()
        return time.perf_counter()
    return time.process_time()


def _seconds(step, reps: int, least: bool = False) -> float:  # noqa: ANN001
    """Median seconds (``_clock``) of ``reps`` steps (the least, for a floor: what the host's other work
    added is never negative)."""
    seconds = []
    for _ in range(reps):
        start = _clock()
        step()
        seconds.append(_clock() - start)
    return round(min(seconds) if least else sorted(seconds)[len(seconds) // 2], 5)


def _measure(step, reps: int, flops: bool = False) -> dict:  # noqa: ANN001
    """Operators (and FLOPs) of the second step; median CPU seconds over ``reps`` more."""
    step()
    with OperatorCount() as ops, FlopCounterMode(display=False) as counter:
        step()
    return {"kernels": sum(ops.kernels.values()), "views": ops.views, "cpu_s": _seconds(step, reps),
            **({"flops": counter.get_total_flops()} if flops else {}), "by_operator": dict(ops.kernels.most_common())}


def _warm(step):  # noqa: ANN001, ANN202
    """``step`` after one call (Adam's state created)."""
    step()
    return step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1085, help="frames a trial at the model rate")
    parser.add_argument("--ks", default="1,2,4,8", help="fold counts batched")
    parser.add_argument("--floor-frames", type=int, default=16, help="frames a trial for the host's floor")
    parser.add_argument("--reps", type=int, default=3, help="timed steps (median)")
    parser.add_argument("--quick", action="store_true", help="smoke run: 200 frames, K = 1 and 2, one timed step")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                        help="cuda: mixed precision as training runs there, wall seconds of the synchronised device "
                             "(results/fold_batch-cuda.json)")
    args = parser.parse_args()
    device = torch.device(args.device)
    if args.quick:
        args.frames, args.ks, args.reps = 200, "1,2", 1
    torch.set_num_threads(1)
    ks = [int(k) for k in args.ks.split(",")]
    load_before = load_average()
    members = {}
    for name in dict.fromkeys(MEMBERS):
        config = TrainConfig(model=name, split="louo", seed=0).resolved()
        print(f"fold batch: {name} alone", file=sys.stderr, flush=True)
        alone = _measure(_alone(name, config, args.frames, device), args.reps, flops=True)
        batched = {}
        for k in ks:
            print(f"fold batch: {name}, {k} folds batched", file=sys.stderr, flush=True)
            batched[str(k)] = _measure(_batched(name, config, args.frames, k, device), args.reps)
        one = batched[str(ks[0])]["by_operator"]
        grows = {op: {k: b["by_operator"].get(op, 0) for k, b in batched.items()}
                 for op in batched[str(ks[-1])]["by_operator"] if batched[str(ks[-1])]["by_operator"][op] > one.get(op, 0)}
        print(f"fold batch: {name}, the host's floor", file=sys.stderr, flush=True)
        floor = {"frames": args.floor_frames}
        for side, step in (("alone", _alone(name, config, args.floor_frames, device, update=False)),
                           ("batched", _batched(name, config, args.floor_frames, 1, device, update=False))):
            _warm(step)
            with OperatorCount() as ops:
                step()
            floor[f"{side}_cpu_s"] = _seconds(step, 10 * args.reps, least=True)
            floor[f"{side}_us_per_operator"] = round(1e6 * floor[f"{side}_cpu_s"] / sum(ops.kernels.values()), 1)
        steps = -(-TRAIN_TRIALS // config.batch_size) * RECIPES[name]["epochs"]  # a fold's steps at the recipe
        members[name] = {"batch_size": config.batch_size, "epochs": RECIPES[name]["epochs"], "steps_per_fold": steps,
                         "count_in_ensemble": MEMBERS.count(name), "alone": alone, "batched": batched, "floor": floor,
                         "operators_growing_with_k": grows}
    cuda = device.type == "cuda"
    write_result("fold_batch" + ("-cuda" if cuda else ""), {
        "machine": machine_info(), "torch": torch.__version__, "threads": 1, "frames": args.frames,
        "floor_frames": args.floor_frames, "inputs": sum(DIMS.values()), "classes": CLASSES, "train_trials": TRAIN_TRIALS, "ks": ks,
        "members": members, "ensemble": list(MEMBERS), "load_1min": [load_before, load_average()],
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"), "quick": args.quick, "device": args.device,
        "clock": "wall, CUDA synchronised" if cuda else "process CPU", "gpu": torch.cuda.get_device_name(0) if cuda else None})


if __name__ == "__main__":
    main()
