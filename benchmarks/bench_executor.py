"""`midas align` throughput through the executors (issue 16): sessions per hour with 1 and 2 local workers
and through a one-node SLURM (the tests' cluster, tests/helpers/slurm_fixture.py), the overhead each
unit pays, and what that projects to on 100 nodes. Not a test: nothing is asserted.

    .venv/bin/python benchmarks/bench_executor.py            # 12 x 2-minute and 6 x 20-minute sessions
    .venv/bin/python benchmarks/bench_executor.py --quick    # 6 x 0.5-minute sessions

Every mode aligns the same sessions with a fresh run folder (``--run-dir``), so the done markers give
each unit's own time (``seconds``: inside the unit, after the process's imports). **Overhead per unit**
= wall × slots / units − mean unit time, slots = the workers (local) or the node's CPUs (SLURM): what a
unit costs beyond its own work (process start-up and imports, scheduling, polling, markers). The SLURM
task start-up alone is timed too: ``midas jobs run-unit`` on a unit already done (start, read the plan,
skip).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

import bench_align  # noqa: E402
from machine import load_average, machine_info, write_result  # noqa: E402

PROJECT_NODES = 100
PROJECT_CORES = 32  # a typical compute node; one unit per core (cpus_per_task = 1)


def midas(args: list[str], env: dict[str, str]) -> float:
    started = time.perf_counter()
    result = subprocess.run([sys.executable, "-m", "midas_cli", *args], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    if result.returncode:
        raise RuntimeError(f"midas {' '.join(args)} exited {result.returncode}: {result.stderr[-2000:]}")
    return time.perf_counter() - started


def unit_seconds(run_dir: Path) -> list[float]:
    return [json.loads(p.read_text())["seconds"] for p in sorted(run_dir.glob("units/*/done.json"))]


def run_mode(name: str, sessions: list[Path], extra: list[str], slots: int, env: dict[str, str], work: Path) -> dict:
    run_dir = work / f"run-{name}"
    load_before = load_average()
    wall = midas(["align", *map(str, sessions), "--run-dir", str(run_dir), *extra], env)
    seconds = unit_seconds(run_dir)
    mean_unit = statistics.mean(seconds)
    return {"mode": name, "args": extra, "units": len(sessions), "slots": slots, "wall_s": round(wall, 2),
            "sessions_per_hour": round(len(sessions) * 3600 / wall), "unit_mean_s": round(mean_unit, 3),
            "overhead_per_unit_s": round(wall * slots / len(sessions) - mean_unit, 3),
            "load_1min_before_after": [load_before, load_average()]}


def measure(work: Path, n: int, minutes: float, cluster_env: dict[str, str]) -> dict:
    """Every mode on ``n`` sessions of ``minutes``."""
    root = work / f"data-{n}x{minutes:g}"
    sessions = [bench_align.write_session(root / f"s{i}", minutes, seed=i) for i in range(n)]
    env = {**os.environ, "MIDAS_PROGRESS_INTERVAL_S": "60"}
    midas(["align", str(sessions[0])], env)  # warm the page cache and the interpreter's files once
    modes = [run_mode("local, 1 worker", sessions, ["--jobs", "1"], 1, env, root),
             run_mode("local, 2 workers", sessions, ["--jobs", "2"], 2, env, root),
             run_mode("one-node SLURM", sessions, ["--executor", "slurm"], os.cpu_count() or 1,
                      {**env, **cluster_env}, root)]
    startup = [midas(["jobs", "run-unit", str(root / "run-one-node SLURM"), "--unit", "0"], {**env, **cluster_env})
               for _ in range(3)]
    slurm = modes[-1]
    per_unit = slurm["unit_mean_s"] + slurm["overhead_per_unit_s"]
    return {"sessions": n, "session_minutes": minutes, "modes": modes,
            "task_startup_s": round(statistics.median(startup), 3),
            "projection": {"nodes": PROJECT_NODES, "cores_per_node": PROJECT_CORES, "unit_s": round(per_unit, 3),
                           "sessions_per_hour": round(PROJECT_NODES * PROJECT_CORES * 3600 / per_unit)}}


def measure_folds(work: Path, trials: int, seconds: float, epochs: int, cluster_env: dict[str, str]) -> dict:
    """`train gestures --split loto --fold all` (one unit per fold: a trial number held out) on a small
    simulated Raven-II dataset, locally with 1 and 2 workers and through the one-node SLURM."""
    data = work / "gestures"
    env = {**os.environ, "MIDAS_PROGRESS_INTERVAL_S": "60"}
    midas(["simulate", "dataset", "--platform", "raven-ii", "--trials", str(trials), "--subjects", "2",
           "--max-seconds", f"{seconds:g}", "--out", str(data)], env)
    midas(["align", *map(str, sorted(p for p in data.iterdir() if p.is_dir()))], env)
    modes = []
    for name, extra, slots, mode_env in (("local, 1 worker", ["--jobs", "1"], 1, env),
                                         ("local, 2 workers", ["--jobs", "2"], 2, env),
                                         ("one-node SLURM", ["--executor", "slurm"], os.cpu_count() or 1,
                                          {**env, **cluster_env})):
        out = work / f"folds-{name.replace(' ', '_').replace(',', '')}"
        load_before = load_average()
        wall = midas(["train", "gestures", str(data), "--split", "loto", "--fold", "all", "--epochs", str(epochs),
                      "--out", str(out), *extra], mode_env)
        seconds_each = unit_seconds(out / "jobs")
        mean_unit = statistics.mean(seconds_each)
        modes.append({"mode": name, "units": len(seconds_each), "slots": slots, "wall_s": round(wall, 2),
                      "folds_per_hour": round(len(seconds_each) * 3600 / wall), "unit_mean_s": round(mean_unit, 3),
                      "overhead_per_unit_s": round(wall * slots / len(seconds_each) - mean_unit, 3),
                      "load_1min_before_after": [load_before, load_average()]})
    return {"trials": trials, "trial_seconds": seconds, "epochs": epochs, "model": "mstcn", "modes": modes}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    options = parser.parse_args()
    sizes = [(6, 0.5)] if options.quick else [(12, 2.0), (6, 20.0)]
    from helpers.slurm_fixture import start_cluster

    with tempfile.TemporaryDirectory(prefix="midas-bench-executor-") as tmp:
        work = Path(tmp)
        cluster_gen = start_cluster(work / "slurm")
        cluster = next(cluster_gen)
        try:
            slurm_env = {"SLURM_CONF": cluster.env["SLURM_CONF"]}
            runs = [measure(work, n, minutes, slurm_env) for n, minutes in sizes]
            folds = measure_folds(work, 4 if options.quick else 8, 20.0 if options.quick else 60.0,
                                  1 if options.quick else 5, slurm_env)
        finally:
            for _ in cluster_gen:
                pass
    write_result("executor", {"quick": options.quick, "machine": machine_info(),
                              "session_streams": "EmHT 4 x 240 Hz, FPS 9 ch x 250 Hz, HandKP 30 Hz, video clock 30 fps",
                              "slurm": "one node = this machine (controller and compute), sched/builtin, "
                                       "select/cons_tres CR_CPU, no cgroups (tests/helpers/slurm_fixture.py)",
                              "runs": runs, "folds": folds})


if __name__ == "__main__":
    main()
