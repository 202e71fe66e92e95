"""Batch throughput (issue 17 goal 4): `midas align` and `midas session verify` over many sessions, given
in one call vs one call per session (what a shell loop does).

One session is simulated (`midas simulate dataset --trials 1 --max-seconds 10`), then copied N times
(default 400) so that every copy is a separate, valid session folder. Each case runs on fresh copies
(align's outputs removed between cases): one `midas align S1 .. SN` against N `midas align Si`
processes, run one after the other like `for s in sessions/*; do midas align "$s"; done`; the same for
`session verify`. Reported: wall seconds, sessions per second, and the fixed cost per process that the
single call saves ((loop - one call) / N).

    .venv/bin/python benchmarks/bench_batch.py             # 400 sessions -> results/batch.json
    .venv/bin/python benchmarks/bench_batch.py --quick     # 20 sessions
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load_average, machine_info, write_result  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CASES = {"align": ["align"], "session verify": ["session", "verify"]}


def _run(args: list[str], env: dict[str, str]) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "midas_cli", *args], check=True, env=env, cwd=REPO,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def _clean(sessions: list[Path]) -> None:
    for session in sessions:
        shutil.rmtree(session / "derived", ignore_errors=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=400, help="How many session folders (default 400).")
    parser.add_argument("--quick", action="store_true", help="20 sessions (a smoke run).")
    args = parser.parse_args()
    count = 20 if args.quick else args.sessions
    env = {**os.environ, "NO_COLOR": "1", "COLUMNS": "120"}
    with tempfile.TemporaryDirectory() as tmp:
        source_root = Path(tmp) / "source"
        subprocess.run([sys.executable, "-m", "midas_cli", "simulate", "dataset", "--trials", "1", "--max-seconds",
                        "10", "--out", str(source_root)], check=True, capture_output=True, env=env, cwd=REPO)
        source = next(p for p in source_root.iterdir() if p.is_dir())
        root = Path(tmp) / "sessions"
        sessions = [root / f"{source.name}-{k:04d}" for k in range(count)]
        for session in sessions:
            shutil.copytree(source, session)
        load_before = load_average()
        results = {}
        for name, command in CASES.items():
            _clean(sessions)
            one_call = _run([*command, *map(str, sessions)], env)
            _clean(sessions)
            loop = sum(_run([*command, str(session)], env) for session in sessions)
            results[name] = {"one_call_s": round(one_call, 2), "loop_s": round(loop, 2),
                             "one_call_sessions_per_s": round(count / one_call, 1),
                             "loop_sessions_per_s": round(count / loop, 1),
                             "speedup": round(loop / one_call, 1),
                             "fixed_cost_per_process_s": round((loop - one_call) / count, 3)}
    write_result("batch", {"machine": machine_info(), "quick": args.quick, "sessions": count, "session_seconds": 10,
                           "load_average_1min_before_after": [load_before, load_average()], "cases": results})


if __name__ == "__main__":
    main()
