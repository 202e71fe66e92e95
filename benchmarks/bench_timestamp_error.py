"""The error of midas's host timestamps on the real serial path, raw and after the clock fit (issue 26 item 3).

The trakSTAR (fob://, 4 sensors at 220 Hz, the most its 115200-baud line carries) and the FPS pedal board
(9 channels at 850 Hz, the most 500000 baud carries) are emulated on pseudo-terminals, each in its own
process, with a send-time log (midas_cli/devices/send_log.py): the monotonic time just after the write of
each record's last byte returned. `python -m midas_cli record` records both through the real drivers.
Each recorded row is matched to its record (the pedal board by its sequence number, the trakSTAR by order:
the FOB records carry no counter) and its error is ``t_host_ns - t_out``, with ``t_out`` put on the
session's clock (the manifest's ``clock.anchor_ns``). The fit is analysis/clockfit.py's, as `midas align
--times fitted` uses it: the pedal board against its ``t_device_us`` counter, the trakSTAR against ``seq``
at its nominal rate (the FOB stream carries no device time). Each condition runs once idle and once with
busy-loop processes on the cores.

    .venv/bin/python benchmarks/bench_timestamp_error.py            # 40 s per condition -> results/timestamp_error.json
    .venv/bin/python benchmarks/bench_timestamp_error.py --quick    # 8 s smoke run
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load_average, machine_info, write_result  # noqa: E402

from midas_cli.analysis.clockfit import fit_stream  # noqa: E402
from midas_cli.devices.send_log import read_send_log  # noqa: E402
from midas_cli.session.reader import Session  # noqa: E402

PY = sys.executable
EMHT_RATE, FPS_RATE = 220, 850  # as bench_record.py: the most each line carries
DEVICES = {"emht": f"fob://{{folder}}/emht?rate={EMHT_RATE}&sensors=4",
           "fps": f"fps://{{folder}}/fps?baud=500000&rate={FPS_RATE}&channels=9"}
GOAL_RAW_P99_MS, GOAL_FITTED_P99_MS = 1.5, 0.5
PAPER_MEAN_MS = {"emht": 43.3, "fps": 12.97}  # Appendix A.1, Table "latencies": source-to-disk means
TAIL_MAX = 20  # cycles the trakSTAR may send after the recorder stopped reading


def serve_emulator(kind: str, folder: str, stop: Any) -> None:
    """Child process: serve one emulator with its send log until ``stop`` is set."""
    from midas_cli.devices.fps.emulator import FpsEmulator, FpsEmulatorConfig
    from midas_cli.devices.trakstar.emulator import EmulatorConfig, TrakstarEmulator

    log = f"{folder}/{kind}.sendlog"
    if kind == "emht":
        emulator: Any = TrakstarEmulator(EmulatorConfig(link=f"{folder}/emht", send_log=log))
    else:
        emulator = FpsEmulator(FpsEmulatorConfig(link=Path(folder) / "fps", send_log=log, keep_samples=False))
    emulator.serve_for(None, stop.is_set)
    emulator.stop()


def start_emulators(folder: Path) -> tuple[list[mp.Process], Any]:
    context = mp.get_context("spawn")
    stop = context.Event()
    procs = [context.Process(target=serve_emulator, args=(kind, str(folder), stop)) for kind in DEVICES]
    for proc in procs:
        proc.start()
    deadline = time.monotonic() + 30
    while not all((folder / kind).exists() for kind in DEVICES):
        if time.monotonic() > deadline or not all(p.is_alive() for p in procs):
            raise RuntimeError("the emulators did not start within 30 s")
        time.sleep(0.05)
    return procs, stop


def start_load(processes: int) -> list[subprocess.Popen]:
    """Busy loops, one per process: the cores are shared with work that never sleeps."""
    return [subprocess.Popen([PY, "-c", "while True: pass"]) for _ in range(processes)]


def record(folder: Path, duration_s: float) -> Path:
    args = [arg for name, url in DEVICES.items() for arg in ("--device", f"{name}={url.format(folder=folder)}")]
    done = subprocess.run([PY, "-m", "midas_cli", "record", *args, "--duration", str(duration_s), "--out",
                           str(folder / "s"), "--subject", "1", "--task", "bench", "--trial", "1", "--no-tui"],
                          capture_output=True, text=True, timeout=duration_s + 120)
    if done.returncode != 0:
        raise RuntimeError(f"midas record failed ({done.returncode}): {done.stderr[-2000:]}")
    return Path(done.stdout.strip().splitlines()[-1])


def match_fps(table: np.ndarray, log: dict[str, np.ndarray]) -> np.ndarray:
    """The send log's row index of every recorded pedal row, by the board's sequence number (one boot:
    a reboot restarts the counter, and the benchmark has none)."""
    if len(log["seq"]) == 0 or np.any(log["boot"] != 0) or np.any(np.diff(log["seq"]) <= 0):
        raise ValueError("the pedal board's send log is not one boot with increasing sequence numbers")
    index = np.searchsorted(log["seq"], table["seq"])
    found = (index < len(log["seq"])) & (log["seq"][np.minimum(index, len(log["seq"]) - 1)] == table["seq"])
    if not found.all():
        raise ValueError(f"{int((~found).sum())} recorded pedal rows are not in the send log")
    return index


def match_emht(table: np.ndarray, log: dict[str, np.ndarray]) -> np.ndarray:
    """The send log's row index of every recorded trakSTAR row, by order: the FOB records carry no counter,
    so row i is the i-th cycle streamed. Valid when no cycle was lost on the way (the caller checks the
    manifest's corrupt and gap counts); the log may run a few cycles past the recording (sent after it
    stopped reading), never short of it."""
    extra = len(log["cycle"]) - len(table)
    if not 0 <= extra <= TAIL_MAX:
        raise ValueError(f"{len(table)} trakSTAR rows against {len(log['cycle'])} streamed cycles: not one to one")
    if np.any(np.diff(table["seq"]) != 1):
        raise ValueError("the trakSTAR rows have sequence gaps: matching by order would be wrong")
    return np.arange(len(table))


def error_figures(error_ns: np.ndarray) -> dict[str, float]:
    """mean and sd (signed), p99 and max of |error|, in ms."""
    ms = error_ns.astype(np.float64) / 1e6
    magnitude = np.abs(ms)
    return {"mean_ms": round(float(ms.mean()), 4), "sd_ms": round(float(ms.std()), 4),
            "p99_ms": round(float(np.percentile(magnitude, 99)), 4), "max_ms": round(float(magnitude.max()), 4)}


def stream_errors(session: Session, name: str, log: dict[str, np.ndarray], anchor_ns: int) -> dict[str, Any]:
    """Raw and fitted error of one stream's rows against the emulator's send times."""
    table = session.read_columns(name)
    index = (match_fps if name == "fps" else match_emht)(table, log)
    out_ns = log["t_out_ns"][index] + anchor_ns
    spec = session.stream_spec(name)
    fit = fit_stream(table, spec.columns, spec.nominal_rate_hz)
    if fit is None or not fit.fitted_samples:
        raise ValueError(f"{name}: the clock fit found nothing to fit")
    raw = table["t_host_ns"] - out_ns
    fitted = fit.fitted_ns - out_ns
    return {"rows": len(table), "sent": len(log["t_out_ns"]), "clock": fit.clock, "drift_ppm": round(fit.drift_ppm, 2),
            "raw": error_figures(raw), "fitted": error_figures(fitted),
            "fitted_about_mean_p99_ms": round(float(np.percentile(np.abs(fitted - fitted.mean()), 99) / 1e6), 4),
            "emulator_late_ms": error_figures(log["t_out_ns"][index] - log["t_due_ns"][index])}


def run_condition(load_processes: int, duration_s: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="midas-bench-ts-") as tmp:
        folder = Path(tmp)
        procs, stop = start_emulators(folder)
        load = start_load(load_processes)
        try:
            time.sleep(2.0 if load_processes else 0.0)  # let the load average see the busy loops start
            load_before = load_average()
            session_path = record(folder, duration_s)
            load_after = load_average()
        finally:
            for proc in load:
                proc.kill()
                proc.wait()
            stop.set()
            for proc in procs:
                proc.join(timeout=20)
        manifest = json.loads((session_path / "manifest.json").read_text(encoding="utf-8"))
        check_no_loss(manifest)
        session = Session.open(session_path)
        streams = {name: stream_errors(session, name, read_send_log(folder / f"{name}.sendlog"),
                                       manifest["clock"]["anchor_ns"]) for name in DEVICES}
    return {"load_processes": load_processes, "duration_s": duration_s,
            "load_average_before_after": [load_before, load_after], "streams": streams}


def check_no_loss(manifest: dict[str, Any]) -> None:
    """Matching rows to records needs every record decoded: no corruption, no gap, no reconnect."""
    for name in DEVICES:
        entry = manifest["streams"][name]
        if entry["corrupt"] or entry["seq_gaps"]["missing"] or entry["dropped"]:
            raise RuntimeError(f"{name}: records were lost ({entry['corrupt']} corrupt, "
                               f"{entry['seq_gaps']['missing']} missing): the rows cannot be matched")
        if sum(e["event"] == "opened" for e in manifest["devices"][name]["events"]) != 1:
            raise RuntimeError(f"{name}: the device reconnected during the recording")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="8 s per condition (smoke run)")
    parser.add_argument("--duration", type=float, default=40.0, help="seconds of recording per condition")
    parser.add_argument("--load", type=int, default=2, help="busy-loop processes in the loaded condition")
    args = parser.parse_args()
    duration = 8.0 if args.quick else args.duration
    conditions = [run_condition(0, duration), run_condition(args.load, duration)]
    write_result("timestamp_error", {
        "machine": machine_info(), "quick": args.quick, "cores": len(os.sched_getaffinity(0)),
        "devices": list(DEVICES.values()), "goal_raw_p99_ms": GOAL_RAW_P99_MS,
        "goal_fitted_p99_ms": GOAL_FITTED_P99_MS, "paper_mean_ms": PAPER_MEAN_MS, "conditions": conditions})


if __name__ == "__main__":
    main()
