"""Recording with live gesture recognition (issue 28): the full rig on emulators at full rate, with and
without `midas record --live-model RUN`, alternately.

Trains a full-size causal MS-TCN++ on simulated EmHT (bench_live_gestures.simulate; --epochs, the weights
do not change the cost), then records --duration seconds (EmHT 4 x 220 Hz over a pty to the trakSTAR
emulator, the FPS board 9 ch x 850 Hz to its emulator, video and HandKP 30 Hz simulated: bench_record's
rig) without and with the model. Per run: each process's CPU over the middle of the recording (% of one
core: recorder, device workers, recognition), every stream's recorded latency p50/p99, loss against the
emulators and queue drops (bench_record.stream_figures); with the model, the recognition latency of every
frame (`t_pred_ns - t_host_ns` of `gestures_live`: the frame's time to its prediction, which includes
waiting for the samples that come after the frame) and the frames the manifest counts as dropped.

    .venv/bin/python benchmarks/bench_live_record.py [--duration 30] [--repeat 2]  # -> results/live_record.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_live_gestures import simulate  # noqa: E402
from bench_record import PY, device_args, start_emulators, steady_state_cpu, stop_emulators, stream_figures  # noqa: E402
from machine import load_average, machine_info, write_result  # noqa: E402

from midas_cli.models.data import DatasetConfig  # noqa: E402
from midas_cli.models.train import TrainConfig, train_run  # noqa: E402


def recognition_latency(session: Path) -> dict:
    """gestures_live: frames written and t_pred - t_host per frame (ms percentiles)."""
    path = session / "streams" / "gestures_live.csv"
    if not path.is_file():
        return {"frames": 0}
    import pandas as pd

    table = pd.read_csv(path)
    ms = (table["t_pred_ns"].to_numpy(np.int64) - table["t_host_ns"].to_numpy(np.int64)) / 1e6
    if not len(ms):
        return {"frames": 0}
    return {"frames": int(len(ms)), **{k: round(float(np.percentile(ms, q)), 2)
                                        for k, q in (("p50_ms", 50), ("p99_ms", 99))}, "max_ms": round(float(ms.max()), 2)}


def run(duration_s: float, model: Path | None) -> dict:
    """One recording on the emulators, with the live model or without."""
    with tempfile.TemporaryDirectory(prefix="midas-bench-liverec-") as tmp:
        folder = Path(tmp)
        emulators = start_emulators(folder)
        load = load_average()
        extra = ["--live-model", str(model)] if model else []
        proc = subprocess.Popen([PY, "-m", "midas_cli", "record", *device_args(folder), "--duration", str(duration_s),
                                 "--out", str(folder / "s"), "--subject", "1", "--task", "bench", "--trial", "1",
                                 "--no-tui", *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        steady = steady_state_cpu(proc, duration_s)
        stdout, stderr = proc.communicate()
        summaries = stop_emulators(emulators, folder)
        if proc.returncode != 0:
            raise RuntimeError(f"midas record failed ({proc.returncode}): {stderr[-2000:]}")
        session = Path(stdout.strip().splitlines()[-1])
        manifest = json.loads((session / "manifest.json").read_text())
        streams = {name: stream_figures(name, entry, summaries) for name, entry in manifest["streams"].items()
                   if name not in ("events", "gestures_live")}
        live = {"latency": recognition_latency(session), "manifest": manifest["streams"].get("gestures_live")} if model else None
    return {"live_model": bool(model), "duration_s": duration_s, "load_average_before_after": [load, load_average()],
            "steady_cpu_percent_of_one_core": steady, "streams": streams, "recognition": live}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=30.0)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--epochs", type=int, default=1)
    args = parser.parse_args()
    runs = []
    with tempfile.TemporaryDirectory(prefix="midas-bench-liverec-model-") as tmp:
        sessions = simulate(Path(tmp) / "data", 30.0)
        model = Path(tmp) / "mstcn"
        train_run(sessions, DatasetConfig(("emht",), ("pos", "ori", "vel")),
                  TrainConfig(model="mstcn", epochs=args.epochs, causal=True), model)
        for k in range(args.repeat):
            for live in (False, True):
                print(f"live record: run {k + 1}, live model {'on' if live else 'off'} ...", file=sys.stderr)
                runs.append(run(args.duration, model if live else None))
                print(json.dumps({"cpu": runs[-1]["steady_cpu_percent_of_one_core"],
                                  "recognition": (runs[-1]["recognition"] or {}).get("latency")}), file=sys.stderr)
    write_result("live_record", {"machine": machine_info(), "model": "mstcn (causal, full size)", "runs": runs})


if __name__ == "__main__":
    main()
