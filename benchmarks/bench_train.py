"""Training epoch time / peak memory of MS-TCN++ and the transformer on CPU, and online inference latency.

Each (model, trial length) case runs in its own subprocess (peak memory = that process's VmHWM): 15
trials of seeded random features with the simulated dataset's layout (EmHT, MTM and PSM 18 features
each, 32 image features; 10 gesture classes), through the real training loop (``models.train.fit``:
Adam, batch size 4, no validation), one epoch timed after one warm-up epoch. Online inference: one
forward pass per new frame over a trailing context (the transformer's 64-frame window; 1024 frames for
MS-TCN++), batch 1, one torch thread, ``torch.no_grad``, 100 calls.

    .venv/bin/python benchmarks/bench_train.py            # trials of 900 and 2700 frames -> results/train.json
    .venv/bin/python benchmarks/bench_train.py --quick    # 150 frames
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load_average, machine_info, write_result  # noqa: E402

TRIALS, CLASSES = 15, 10
MODALITY_DIMS = {"emht": 18, "mtm": 18, "psm": 18, "image": 32}
ONLINE_CONTEXT = {"mstcn": 1024, "transformer": 64}


def case(model_name: str, frames: int, epochs: int) -> dict:
    """Runs inside the child: time ``epochs`` epochs after a warm-up, then online inference."""
    import torch

    from midas_cli.models.train import Sequences, TrainConfig, build_model, fit

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    dim = sum(MODALITY_DIMS.values())
    seqs = Sequences([("t", i, 0) for i in range(TRIALS)],
                     [rng.normal(size=(frames, dim)).astype(np.float32) for _ in range(TRIALS)],
                     [rng.integers(0, CLASSES, frames) for _ in range(TRIALS)])
    empty = Sequences([], [], [])
    model, _ = build_model(model_name, MODALITY_DIMS, CLASSES, {})
    fit(model, seqs, empty, TrainConfig(model=model_name, epochs=1), torch.device("cpu"))  # warm-up
    t0 = time.monotonic()
    fit(model, seqs, empty, TrainConfig(model=model_name, epochs=epochs), torch.device("cpu"))
    epoch_s = (time.monotonic() - t0) / epochs
    return {"model": model_name, "frames_per_trial": frames, "trials": TRIALS, "epoch_s": round(epoch_s, 3),
            "torch_threads": torch.get_num_threads(), "online": online_latency(model, dim, ONLINE_CONTEXT[model_name])}


def online_latency(model, dim: int, context: int, calls: int = 100) -> dict:  # noqa: ANN001
    import torch

    model.eval()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one frame at a time beside a recorder: no OpenMP team to wake (or wait for)
    x, mask = torch.randn(1, dim, context), torch.ones(1, context, dtype=torch.bool)
    times = []
    with torch.no_grad():
        for _ in range(calls + 5):
            t0 = time.perf_counter()
            model.frame_logits(model(x, mask))[0, :, -1].argmax()
            times.append((time.perf_counter() - t0) * 1e3)
    torch.set_num_threads(threads)
    ms = np.array(times[5:])
    return {"context_frames": context, "torch_threads": 1, "p50_ms": round(float(np.percentile(ms, 50)), 3),
            "p99_ms": round(float(np.percentile(ms, 99)), 3), "max_ms": round(float(ms.max()), 3)}


def run_child(model_name: str, frames: int, epochs: int) -> dict:
    load = load_average()
    proc = subprocess.run([sys.executable, __file__, "--case", model_name, str(frames), str(epochs)],
                          capture_output=True, text=True, check=True)
    return {"load_average_before_after": [load, load_average()], **json.loads(proc.stdout.strip().splitlines()[-1])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="150-frame trials")
    parser.add_argument("--case", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.case:
        result = case(args.case[0], int(args.case[1]), int(args.case[2]))
        hwm = [line for line in open("/proc/self/status") if line.startswith("VmHWM:")][0].split()[1]
        print(json.dumps({**result, "peak_rss_mib": round(int(hwm) / 1024, 1)}))
        return
    sizes, epochs = ([150], 1) if args.quick else ([900, 2700], 1)
    runs = []
    for model_name in ("mstcn", "transformer"):
        for frames in sizes:
            print(f"train: {model_name}, {TRIALS} trials x {frames} frames ...", file=sys.stderr)
            runs.append(run_child(model_name, frames, epochs))
    write_result("train", {"machine": machine_info(), "quick": args.quick, "modality_dims": MODALITY_DIMS,
                           "classes": CLASSES, "timed_epochs": epochs, "runs": runs})


if __name__ == "__main__":
    main()
