"""MS-TCN++ training epoch and inference per frame: midas against a reference written from the paper.

Reference: a minimal MS-TCN++ written here from Li, Abu Farha, Liu, Cheng, Gall, "MS-TCN++: Multi-Stage
Temporal Convolutional Network for Action Segmentation" (TPAMI 2020), laid out the way the authors'
published code is structured (not copied from it): a prediction-generation stage of dual dilated
residual layers (3-tap convolutions of dilation 2^(L-1-l) and 2^l, concatenated, fused by a 1x1
convolution, ReLU, dropout, residual), refinement stages of single dilated residual layers (3-tap
dilated convolution, ReLU, 1x1, dropout, residual) fed the softmax of the previous stage, every stage
output multiplied by an all-ones mask (batch 1); loss = sum over stages of cross-entropy + lambda x the
mean truncated MSE (clamped at tau^2) of consecutive frames' log-softmax (the earlier frame detached);
Adam; batch 1, one trial per step; the plain loop: model.train(), per trial zero_grad, forward, loss over
stages, backward, step. Its hyper-parameters (layers, stages, feature maps, dropout, lambda, tau, lr,
batch size) are read from midas (``MSTCNConfig`` defaults, ``RECIPES["mstcn"]``), its parameter count must
equal midas's, and with midas's weights copied in it must give midas's outputs (eval mode), or the
benchmark fails.

Data: the same arrays for both, synthetic and JIGSAWS-sized (39 trials, frame counts uniform in
2,700-3,840 (mean ~3,270), 76 columns, 10 classes, piecewise-constant labels, seed 0), normalised like
midas's training-set normaliser. midas's side is its real loop, ``models.train.fit`` with the MS-TCN++
recipe (as ``midas train gestures`` calls it, without dataset building, split and run-folder I/O), one
epoch per call; the reference is its loop above. Same ``torch.set_num_threads``, same initial weights; one
warm-up epoch each, then N epoch pairs interleaved, midas first in odd pairs and the reference first in
even ones (so a load that drifts during the run does not favour one side); median epoch seconds each,
ratio midas/reference (and the median of the per-pair ratios). On a shared machine run it with
``--threads 1``: with more OpenMP threads than free cores, waiting threads swamp both sides.

Inference, batch 1, one torch thread, ``torch.no_grad``, eval mode:
* online (midas's online mode as ``bench_train.py`` measures it): for each new frame, one forward pass over
  the trailing ``bench_train.ONLINE_CONTEXT["mstcn"]`` (1024) frames, keeping the last frame's class;
  milliseconds per call = latency per new frame. The reference does the same on the same window; calls
  interleaved one by one.
* offline: one forward pass over a whole trial (~3,270 frames), divided by its frames: throughput cost per
  frame in microseconds, not a latency.

    .venv/bin/python benchmarks/bench_mstcn_reference.py            # 3 timed epochs each -> results/mstcn_reference.json
    .venv/bin/python benchmarks/bench_mstcn_reference.py --quick    # 1 timed epoch each, 6 trials
    .venv/bin/python benchmarks/bench_mstcn_reference.py --profile  # also torch.profiler top ops of one step each
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load_average, machine_info, write_result  # noqa: E402

TRIALS, MIN_FRAMES, MAX_FRAMES, COLUMNS, CLASSES, SEED = 39, 2700, 3840, 76, 10, 0
QUICK_TRIALS = 6


# ---------------------------------------------------------------- reference network (from the paper)

class RefDualDilatedLayer(nn.Module):
    def __init__(self, maps: int, layer: int, layers: int, dropout: float) -> None:
        super().__init__()
        self.conv_dilated_1 = nn.Conv1d(maps, maps, 3, padding=2 ** (layers - 1 - layer), dilation=2 ** (layers - 1 - layer))
        self.conv_dilated_2 = nn.Conv1d(maps, maps, 3, padding=2 ** layer, dilation=2 ** layer)
        self.conv_fusion = nn.Conv1d(2 * maps, maps, 1)
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        out = self.conv_fusion(torch.cat([self.conv_dilated_1(x), self.conv_dilated_2(x)], 1))
        out = self.dropout(F.relu(out))
        return (x + out) * mask


class RefPredictionGeneration(nn.Module):
    def __init__(self, layers: int, maps: int, dim: int, classes: int, dropout: float) -> None:
        super().__init__()
        self.conv_in = nn.Conv1d(dim, maps, 1)
        self.layers = nn.ModuleList(RefDualDilatedLayer(maps, i, layers, dropout) for i in range(layers))
        self.conv_out = nn.Conv1d(maps, classes, 1)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        out = self.conv_in(x)
        for layer in self.layers:
            out = layer(out, mask)
        return self.conv_out(out) * mask


class RefDilatedResidualLayer(nn.Module):
    def __init__(self, maps: int, dilation: int, dropout: float) -> None:
        super().__init__()
        self.conv_dilated = nn.Conv1d(maps, maps, 3, padding=dilation, dilation=dilation)
        self.conv_1x1 = nn.Conv1d(maps, maps, 1)
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        out = self.dropout(self.conv_1x1(F.relu(self.conv_dilated(x))))
        return (x + out) * mask


class RefRefinementStage(nn.Module):
    def __init__(self, layers: int, maps: int, classes: int, dropout: float) -> None:
        super().__init__()
        self.conv_in = nn.Conv1d(classes, maps, 1)
        self.layers = nn.ModuleList(RefDilatedResidualLayer(maps, 2 ** i, dropout) for i in range(layers))
        self.conv_out = nn.Conv1d(maps, classes, 1)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        out = self.conv_in(x)
        for layer in self.layers:
            out = layer(out, mask)
        return self.conv_out(out) * mask


class ReferenceMSTCN(nn.Module):
    """x (1, D, T), mask (1, 1, T) of ones; returns the logits of every stage (S, 1, C, T)."""

    def __init__(self, pg_layers: int, stages: int, r_layers: int, maps: int, dim: int, classes: int,
                 dropout: float) -> None:
        super().__init__()
        self.pg = RefPredictionGeneration(pg_layers, maps, dim, classes, dropout)
        self.refinements = nn.ModuleList(RefRefinementStage(r_layers, maps, classes, dropout) for _ in range(stages))

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        out = self.pg(x, mask)
        outputs = [out]
        for stage in self.refinements:
            out = stage(F.softmax(out, dim=1) * mask, mask)
            outputs.append(out)
        return torch.stack(outputs)


def reference_loss(stages: torch.Tensor, target: torch.Tensor, lam: float, tau: float) -> torch.Tensor:
    """Paper eq.: sum over stages of CE + lambda x mean over frames and classes of min(delta^2, tau^2),
    delta = log y_t,c - log y_t-1,c with the earlier frame's gradient stopped."""
    loss = stages.new_zeros(())
    for p in stages:  # p (1, C, T)
        loss = loss + F.cross_entropy(p.transpose(2, 1).reshape(-1, p.shape[1]), target.view(-1))
        delta = F.log_softmax(p[:, :, 1:], dim=1) - F.log_softmax(p.detach()[:, :, :-1], dim=1)
        loss = loss + lam * torch.mean(torch.clamp(delta ** 2, min=0, max=tau ** 2))
    return loss


def reference_epoch(model: ReferenceMSTCN, optimiser: torch.optim.Optimizer, xs: list[np.ndarray],
                    ys: list[np.ndarray], order: np.ndarray, lam: float, tau: float) -> float:
    """One epoch of the plain loop, batch 1: inputs built from the (T, D) arrays per step, as a batch
    generator hands them over; returns the mean loss."""
    model.train()
    total = 0.0
    for i in order:
        x = torch.from_numpy(np.ascontiguousarray(xs[i].T)).unsqueeze(0)  # (T, D) -> (1, D, T)
        y = torch.from_numpy(ys[i]).unsqueeze(0)
        mask = torch.ones(1, 1, x.shape[-1])
        optimiser.zero_grad()
        loss = reference_loss(model(x, mask), y, lam, tau)
        loss.backward()
        optimiser.step()
        total += loss.item()
    return total / len(order)


def copy_midas_weights(midas: nn.Module, ref: ReferenceMSTCN) -> None:
    """midas's parameters into the reference, layer by layer by meaning (not by name or order); every
    parameter of midas must be copied exactly once."""
    copied = []

    def put(dst: nn.Conv1d, src: nn.Conv1d) -> None:
        if dst.dilation != src.dilation or dst.weight.shape != src.weight.shape:
            raise SystemExit(f"layers do not match: {dst} against {src}")
        dst.weight.data.copy_(src.weight.data)
        dst.bias.data.copy_(src.bias.data)
        copied.extend([id(src.weight), id(src.bias)])

    g = midas.generation
    put(ref.pg.conv_in, g.conv_in)
    put(ref.pg.conv_out, g.conv_out)
    for r, m in zip(ref.pg.layers, g.layers):
        put(r.conv_dilated_1, m.conv_large)  # 2^(L-1-l), first in the concatenation in both
        put(r.conv_dilated_2, m.conv_small)  # 2^l
        put(r.conv_fusion, m.fusion)
    for rs, ms in zip(ref.refinements, midas.refinements):
        put(rs.conv_in, ms.conv_in)
        put(rs.conv_out, ms.conv_out)
        for r, m in zip(rs.layers, ms.layers):
            put(r.conv_dilated, m.conv_dilated)
            put(r.conv_1x1, m.conv_1x1)
    if sorted(copied) != sorted(id(p) for p in midas.parameters()):
        raise SystemExit("the reference does not hold every midas parameter exactly once")


# ---------------------------------------------------------------- data, checks, timings

def synthetic_arrays(trials: int, seed: int = SEED) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """JIGSAWS-sized arrays: x (T, 76) float32 normalised over all frames, y (T,) int64 in 0..9,
    piecewise-constant (segments of 30-400 frames) with class-dependent feature means."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(0.0, 1.0, (CLASSES, COLUMNS))
    xs, ys = [], []
    for _ in range(trials):
        t = int(rng.integers(MIN_FRAMES, MAX_FRAMES + 1))
        y = np.empty(t, dtype=np.int64)
        start = 0
        while start < t:
            stop = min(t, start + int(rng.integers(30, 401)))
            y[start:stop] = rng.integers(0, CLASSES)
            start = stop
        xs.append(centres[y] + rng.normal(0.0, 1.5, (t, COLUMNS)))
        ys.append(y)
    from midas_cli.models.data import Normaliser
    norm = Normaliser.fit(xs)
    return [norm.apply(x).astype(np.float32) for x in xs], ys


def check_same_network(midas: nn.Module, ref: ReferenceMSTCN, x: np.ndarray) -> dict:
    n_midas = sum(p.numel() for p in midas.parameters())
    n_ref = sum(p.numel() for p in ref.parameters())
    print(f"parameters: midas {n_midas}, reference {n_ref}", file=sys.stderr)
    if n_midas != n_ref:
        raise SystemExit(f"parameter counts differ: midas {n_midas}, reference {n_ref}: not the same network")
    copy_midas_weights(midas, ref)
    midas.eval()
    ref.eval()
    inputs = torch.from_numpy(np.ascontiguousarray(x.T))[None]
    with torch.no_grad():
        a = midas(inputs, torch.ones(1, x.shape[0], dtype=torch.bool))
        b = ref(inputs, torch.ones(1, 1, x.shape[0]))
    diff = float((a - b).abs().max())
    if a.shape != b.shape or diff > 1e-4:
        raise SystemExit(f"the reference does not compute midas's function (max |diff| {diff})")
    return {"parameters_midas": n_midas, "parameters_reference": n_ref, "eval_outputs_max_abs_diff": diff,
            "frames_checked": int(x.shape[0])}


def latencies(fns: dict, calls: int) -> dict[str, list[float]]:
    """Seconds per call of each no-argument callable, interleaved call by call (order alternating)
    after 3 untimed calls each."""
    names = list(fns)
    times: dict[str, list[float]] = {name: [] for name in names}
    with torch.no_grad():
        for i in range(calls + 3):
            for name in (names if i % 2 == 0 else names[::-1]):
                t0 = time.perf_counter()
                fns[name]()
                if i >= 3:
                    times[name].append(time.perf_counter() - t0)
    return times


def inference(midas: nn.Module, ref: ReferenceMSTCN, xs: list[np.ndarray], context: int, calls: int,
              repeats: int) -> dict:
    midas.eval()
    ref.eval()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    window = torch.from_numpy(np.ascontiguousarray(xs[0][-context:].T))[None]  # (1, D, context)
    w_mask, w_ones = torch.ones(1, context, dtype=torch.bool), torch.ones(1, 1, context)
    trial = torch.from_numpy(np.ascontiguousarray(xs[0].T))[None]
    t_mask, t_ones = torch.ones(1, trial.shape[-1], dtype=torch.bool), torch.ones(1, 1, trial.shape[-1])
    on = latencies({"midas": lambda: midas.frame_logits(midas(window, w_mask))[0, :, -1].argmax(),
                    "reference": lambda: ref(window, w_ones)[-1][0, :, -1].argmax()}, calls)
    off = latencies({"midas": lambda: midas.frame_logits(midas(trial, t_mask))[0].argmax(dim=0),
                     "reference": lambda: ref(trial, t_ones)[-1][0].argmax(dim=0)}, repeats)
    torch.set_num_threads(threads)
    frames = int(trial.shape[-1])

    def ms(v: list[float]) -> dict:
        a = np.array(v) * 1e3
        return {"p50_ms": round(float(np.percentile(a, 50)), 3), "p99_ms": round(float(np.percentile(a, 99)), 3)}
    out = {"torch_threads": 1, "online_context_frames": context, "online_calls": calls, "offline_frames": frames,
           "offline_repeats": repeats}
    for side in ("midas", "reference"):
        out[side] = {"online": ms(on[side]),
                     "offline_us_per_frame": round(statistics.median(off[side]) / frames * 1e6, 2)}
    out["online_ratio_p50"] = round(out["midas"]["online"]["p50_ms"] / out["reference"]["online"]["p50_ms"], 3)
    out["offline_ratio"] = round(out["midas"]["offline_us_per_frame"] / out["reference"]["offline_us_per_frame"], 3)
    return out


def profile_step(name: str, step) -> list[dict]:  # noqa: ANN001 - a no-argument callable
    """torch.profiler over one training step: the ten ops with the most self CPU time."""
    from torch.profiler import ProfilerActivity, profile
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        step()
    events = sorted(prof.key_averages(), key=lambda e: -e.self_cpu_time_total)[:10]
    print(f"--- {name}: one step\n" + prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=12),
          file=sys.stderr)
    return [{"op": e.key, "self_cpu_ms": round(e.self_cpu_time_total / 1e3, 2), "calls": e.count} for e in events]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"1 timed epoch each on {QUICK_TRIALS} trials")
    parser.add_argument("--epochs", type=int, help="timed epochs each (default 3, --quick 1)")
    parser.add_argument("--trials", type=int, help=f"trials (default {TRIALS}, --quick {QUICK_TRIALS})")
    parser.add_argument("--threads", type=int, help="torch threads for training, both sides (default: torch's)")
    parser.add_argument("--profile", action="store_true", help="torch.profiler of one training step each")
    parser.add_argument("--name", default="mstcn_reference", help="results/<name>.json")
    args = parser.parse_args()
    from bench_train import ONLINE_CONTEXT
    from midas_cli.models.mstcn import MSTCNConfig
    from midas_cli.models.train import RECIPES, Sequences, TrainConfig, build_model, fit

    epochs = args.epochs or (1 if args.quick else 3)
    trials = args.trials or (QUICK_TRIALS if args.quick else TRIALS)
    if args.threads:
        torch.set_num_threads(args.threads)
    threads = torch.get_num_threads()
    recipe = RECIPES["mstcn"]
    if recipe["batch_size"] != 1:
        raise SystemExit(f"midas's MS-TCN++ recipe has batch {recipe['batch_size']}; the reference loop is batch 1")
    xs, ys = synthetic_arrays(trials)
    torch.manual_seed(SEED)
    midas, cfg_dict = build_model("mstcn", {"columns": COLUMNS}, CLASSES, {})
    cfg = MSTCNConfig(**cfg_dict)
    ref = ReferenceMSTCN(cfg.pg_layers, cfg.refinement_stages, cfg.refinement_layers, cfg.feature_maps,
                         cfg.in_features, cfg.n_classes, cfg.dropout)
    check = check_same_network(midas, ref, xs[0][:500])  # also copies midas's initial weights into ref
    ref_opt = torch.optim.Adam(ref.parameters(), lr=recipe["lr"])
    seqs, empty = Sequences([(f"synthetic{i}", 0, len(y)) for i, y in enumerate(ys)], xs, ys), Sequences([], [], [])
    order_rng = np.random.default_rng(SEED)

    def run_midas(epoch: int) -> float:
        t0 = time.perf_counter()
        fit(midas, seqs, empty, TrainConfig(model="mstcn", epochs=1, seed=epoch), torch.device("cpu"))
        return time.perf_counter() - t0

    def run_ref(epoch: int) -> float:
        t0 = time.perf_counter()
        reference_epoch(ref, ref_opt, xs, ys, order_rng.permutation(len(xs)), cfg.smoothing_weight, cfg.tau)
        return time.perf_counter() - t0

    load_before = load_average()
    print(f"{trials} trials, {sum(len(y) for y in ys)} frames, {threads} torch threads; warm-up ...", file=sys.stderr)
    warm = {"midas": round(run_midas(0), 2), "reference": round(run_ref(0), 2)}
    times: dict[str, list[float]] = {"midas": [], "reference": []}
    loads = []
    for epoch in range(1, epochs + 1):  # midas first in odd pairs, the reference first in even ones
        loads.append(load_average())
        for side in (("midas", "reference") if epoch % 2 else ("reference", "midas")):
            times[side].append(round(run_midas(epoch) if side == "midas" else run_ref(epoch), 3))
        print(f"epoch {epoch}: midas {times['midas'][-1]:.2f} s, reference {times['reference'][-1]:.2f} s, "
              f"load {loads[-1]}", file=sys.stderr)
    load_after = load_average()
    median = {side: round(statistics.median(v), 3) for side, v in times.items()}
    pair_ratios = [round(a / b, 3) for a, b in zip(times["midas"], times["reference"])]
    profile = None
    if args.profile:
        one = Sequences(seqs.units[:1], xs[:1], ys[:1])
        profile = {"midas": profile_step("midas", lambda: fit(midas, one, empty, TrainConfig(model="mstcn", epochs=1),
                                                              torch.device("cpu"))),
                   "reference": profile_step("reference", lambda: reference_epoch(
                       ref, ref_opt, xs, ys, np.array([0]), cfg.smoothing_weight, cfg.tau))}
    print("inference ...", file=sys.stderr)
    infer_load = load_average()
    infer = inference(midas, ref, xs, ONLINE_CONTEXT["mstcn"], 30 if args.quick else 100, 2 if args.quick else 5)
    infer["load_average_before_after"] = [infer_load, load_average()]
    frames = [len(y) for y in ys]
    write_result(args.name, {
        "machine": machine_info(), "quick": args.quick, "torch": str(torch.__version__), "torch_threads": threads,
        "data": {"trials": trials, "frames_total": int(sum(frames)), "frames_per_trial_mean": round(float(np.mean(frames)), 1),
                 "frames_min_max": [int(min(frames)), int(max(frames))], "columns": COLUMNS, "classes": CLASSES,
                 "seed": SEED, "kind": "synthetic arrays, the same for both sides"},
        "hyper_parameters": {**{k: v for k, v in cfg_dict.items() if k not in ("in_features", "n_classes")},
                             "lr": recipe["lr"], "batch_size": recipe["batch_size"], "optimiser": "Adam"},
        "check": check, "warmup_epoch_s": warm, "timed_epochs": epochs, "epoch_s": times, "epoch_s_median": median,
        "ratio_midas_over_reference": round(median["midas"] / median["reference"], 3),
        "pair_ratios": pair_ratios, "pair_ratio_median": round(statistics.median(pair_ratios), 3),
        "load_average_before_after": [load_before, load_after], "load_average_per_epoch_pair": loads,
        "inference": infer, "profile": profile})


if __name__ == "__main__":
    main()
