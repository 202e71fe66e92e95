"""Start-up of light commands as a ratio to a bare interpreter (issue 17 goal 2), median of paired runs.

Each case is a whole `python -m midas_cli ...` process, run in turn with `python -c pass` (A B A B ...);
the ratio is taken pair by pair (so a drift in the machine's speed cancels) and the median kept. The
session commands run on a small session made with `midas simulate dataset --trials 1 --max-seconds 5`.
Goals: --version and --help <= 3x, session info|list|verify <= 6x.

    .venv/bin/python benchmarks/bench_startup.py            # 10 pairs per case -> results/startup.json
    .venv/bin/python benchmarks/bench_startup.py --runs 3   # quicker
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load_average, machine_info, write_result  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
GOALS = {"--version": 3.0, "--help": 3.0, "session info": 6.0, "session list": 6.0, "session verify": 6.0}


def _seconds(command: list[str], env: dict[str, str]) -> float:
    start = time.perf_counter()
    subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, cwd=REPO, check=False)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10, help="Pairs per case (the median is reported).")
    parser.add_argument("--quick", action="store_true", help="3 pairs per case (a smoke run).")
    args = parser.parse_args()
    runs = 3 if args.quick else args.runs
    env = {**os.environ, "NO_COLOR": "1", "COLUMNS": "80"}
    midas = [sys.executable, "-m", "midas_cli"]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "sessions"
        subprocess.run([*midas, "simulate", "dataset", "--trials", "1", "--max-seconds", "5", "--out", str(root)],
                       check=True, capture_output=True, env=env, cwd=REPO)
        session = str(next(p for p in root.iterdir() if p.is_dir()))
        cases = {"--version": ["--version"], "--help": ["--help"], "session info": ["session", "info", session],
                 "session list": ["session", "list", str(root)], "session verify": ["session", "verify", session]}
        bare = [sys.executable, "-c", "pass"]
        load_before = load_average()
        results = {}
        for name, case in cases.items():
            _seconds([*midas, *case], env), _seconds(bare, env)  # warm-up (page cache, .pyc)
            pairs = [(_seconds([*midas, *case], env), _seconds(bare, env)) for _ in range(runs)]
            ratios = [a / b for a, b in pairs]
            results[name] = {"command": "midas " + " ".join(case).replace(tmp, "$TMP"),
                             "median_s": round(statistics.median(a for a, _ in pairs), 4),
                             "bare_median_s": round(statistics.median(b for _, b in pairs), 4),
                             "ratio_median": round(statistics.median(ratios), 2),
                             "ratio_min": round(min(ratios), 2), "ratio_max": round(max(ratios), 2),
                             "goal": GOALS[name], "meets_goal": statistics.median(ratios) <= GOALS[name]}
    write_result("startup", {"machine": machine_info(), "runs": runs, "quick": args.quick,
                             "load_average_1min_before_after": [load_before, load_average()], "cases": results})


if __name__ == "__main__":
    main()
