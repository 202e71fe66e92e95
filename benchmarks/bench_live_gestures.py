"""Live gesture recognition's cost per frame on the CPU (issue 28): `LiveFeed` fed a recorded session's
EmHT rows in 10 ms chunks, as a recorder hands them over, with full-size causal models.

Simulates Raven-II trials (`midas simulate dataset`), aligns them, trains each causal model at its
default size for --epochs (the weights do not change the cost; accuracy is not measured here), then
replays one session's EmHT rows into `load_live_model(run)` in chunks of 10 ms of host time and times
every `ready()` call. Per frame: the latency of the calls that produced exactly one frame (features +
one incremental model step + the run's decoding; p50 / p99 / max), the model step alone
(`frame_stepper`, same features), the state the stepper holds, and the decoding step alone (the run's
clean-up at `train gestures`' defaults, `--min-segment auto --grammar auto`, run live by
`postprocess.OnlineDecoder`). One torch / BLAS thread, as a recorder's worker would run.

    .venv/bin/python benchmarks/bench_live_gestures.py [--seconds 60] [--models mstcn,transformer] \
        [--epochs 1]     # -> results/live_gestures.json
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy / torch load their thread pools
sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load_average, machine_info, write_result  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from midas_cli.analysis.align import align_and_write  # noqa: E402
from midas_cli.analysis.live_features import load_run  # noqa: E402
from midas_cli.analysis.live_gestures import LiveFeed, load_live_model  # noqa: E402
from midas_cli.models.data import DatasetConfig  # noqa: E402
from midas_cli.models.streaming import frame_stepper  # noqa: E402
from midas_cli.models.train import TrainConfig, train_run  # noqa: E402
from midas_cli.session.reader import Session  # noqa: E402

CHUNK_NS = 10_000_000  # a recorder hands rows over about every 10 ms


def simulate(root: Path, seconds: float) -> list[Path]:
    result = subprocess.run([sys.executable, "-m", "midas_cli", "simulate", "dataset", "--platform", "raven-ii",
                             "--trials", "2", "--max-seconds", str(seconds), "--seed", "5", "--out", str(root)],
                            check=True, capture_output=True, text=True)
    sessions = [Path(line) for line in result.stdout.split() if line.strip()]
    for session in sessions:
        align_and_write(session)
    return sessions


def percentiles(values_s: list[float]) -> dict[str, float]:
    ms = np.asarray(values_s) * 1e3
    return {"n": int(len(ms)), "p50_ms": round(float(np.percentile(ms, 50)), 3),
            "p99_ms": round(float(np.percentile(ms, 99)), 3), "max_ms": round(float(ms.max()), 3)}


def replay(feed: LiveFeed, session: Path) -> dict:
    """Feed the session's rows of every needed stream in 10 ms chunks of host time; time each ready()."""
    recorded = Session.open(session)
    rows = {}
    for stream, columns in feed.spec.streams.items():
        data = recorded.read_columns(stream)
        rows[stream] = (np.asarray(data["t_host_ns"]), np.column_stack([data[c] for c in columns]))
    start = min(int(t[0]) for t, _ in rows.values())
    end = max(int(t[-1]) for t, _ in rows.values())
    one_frame, other, frames = [], 0, 0
    for edge in range(start + CHUNK_NS, end + CHUNK_NS, CHUNK_NS):
        for stream, (t, values) in rows.items():
            lo, hi = np.searchsorted(t, [edge - CHUNK_NS, edge], side="right")
            if hi > lo:
                feed.add(stream, t[lo:hi], values[lo:hi])
        began = time.perf_counter()
        made = feed.ready()
        took = time.perf_counter() - began
        frames += len(made)
        if len(made) == 1:
            one_frame.append(took)
        elif made:
            other += 1
    return {"frames": frames, "calls_with_several_frames": other, "per_frame": percentiles(one_frame)}


def model_step_only(run: Path, frames: int) -> dict:
    """The incremental model step alone on random inputs of the model's width."""
    stepper = frame_stepper(load_run(run).model)
    width = sum(len(v) for v in torch.load(run / "checkpoint.pt", weights_only=True)["feature_names"].values())
    x = np.random.default_rng(0).normal(size=(frames, width)).astype(np.float32)
    times = []
    for frame in x:
        began = time.perf_counter()
        stepper.step(frame)
        times.append(time.perf_counter() - began)
    return {**percentiles(times), "state_floats": stepper.state_floats()}


def decoding_step_only(run: Path, frames: int) -> dict:
    """The run's live decoding alone (one ``OnlineDecoder.step`` a frame) on random log-probabilities."""
    live = load_run(run)
    decoder = live.decoding.decoder(len(live.classes))
    log_probs = np.log(np.random.default_rng(1).dirichlet(np.ones(len(live.classes)), size=frames))
    times = []
    for row in log_probs:
        began = time.perf_counter()
        decoder.step(row)
        times.append(time.perf_counter() - began)
    return {**percentiles(times), **live.decoding.manifest(), "classes": len(live.classes)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="length of each simulated trial")
    parser.add_argument("--models", default="mstcn,transformer")
    parser.add_argument("--epochs", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(1)
    report = {"machine": machine_info(), "load_average_1min_before": load_average(), "seconds": args.seconds,
              "chunk_ms": CHUNK_NS / 1e6, "models": {}}
    with tempfile.TemporaryDirectory(prefix="midas-bench-live-") as tmp:
        sessions = simulate(Path(tmp) / "data", args.seconds)
        for model in args.models.split(","):
            run = Path(tmp) / model
            train_run(sessions, DatasetConfig(("emht",), ("pos", "ori", "vel")),
                      TrainConfig(model=model, epochs=args.epochs, causal=True, min_segment="auto", grammar="auto"), run)
            rates = {s: Session.open(sessions[0]).stream_spec(s).nominal_rate_hz for s in ("emht",)}
            feed = load_live_model(run, rates)
            report["models"][model] = {"rate_hz": feed.spec.rate_hz, "live": replay(feed, sessions[0]),
                                       "model_step": model_step_only(run, 1000),
                                       "decoding_step": decoding_step_only(run, 1000)}
    report["load_average_1min_after"] = load_average()
    write_result("live_gestures", report)


if __name__ == "__main__":
    main()
