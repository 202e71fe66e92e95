"""The error of midas's host timestamps on the real serial path, raw and after the clock fit (issue 26 item 3).

The trakSTAR (fob://, 4 sensors at 220 Hz, the most its 115200-baud line carries) and the FPS pedal board
(9 channels at 850 Hz, the most 500000 baud carries) are emulated on pseudo-terminals, each in its own
process, with a send-time log (midas_cli/devices/send_log.py): the monotonic time just after the write of
each record's last byte returned. `python -m midas_cli record` records both through the real drivers.
Each recorded row is matched to its record (the pedal board by its sequence number, the trakSTAR by order:
the FOB records carry no counter) and its error is ``t_host_ns - t_out``, with ``t_out`` put on the
session's clock (the manifest's ``clock.anchor_ns``). The fit is analysis/clockfit.py's, as `midas align
--times fitted` uses it: the pedal board against its ``t_device_us`` counter, the trakSTAR against ``seq``
at its nominal rate (the FOB stream carries no device time). Beside each recording, a bare reader
(select, os.read, stamp: no midas) reads the pedal board for a while: what the kernel and the scheduler
alone give on this machine at that moment, against which midas's share can be told. Conditions: idle; with busy-loop processes
on the cores; loaded with the whole recorder at a higher priority (``nice -n -10``, where permitted), to
show how much of the error is the wait for a CPU; and loaded with only the device workers at that priority
(``midas record --priority high``, what midas offers; the recorder at nice 0). The emulators stand in for hardware, which is never
late: they run at ``nice -n -10`` where permitted, and how late they still were (``t_out - t_due``) is
reported, because the fit works on the device's clock (the due times) while the error is taken
against the send times.

    .venv/bin/python benchmarks/bench_timestamp_error.py            # 40 s per condition -> results/timestamp_error.json
    .venv/bin/python benchmarks/bench_timestamp_error.py --quick    # 8 s smoke run
    .venv/bin/python benchmarks/bench_timestamp_error.py --conditions loaded,loaded-recorder-nice,loaded-workers-high \
        --duration 20 --name timestamp_error_priority                # -> results/timestamp_error_priority.json
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import select
import subprocess
import sys
import tempfile
import time
import tty
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load_average, machine_info, write_result  # noqa: E402

from midas_cli.analysis.clockfit import fit_stream  # noqa: E402
from midas_cli.devices.fps.protocol import LineDecoder, Sample, encode_command  # noqa: E402
from midas_cli.devices.send_log import read_send_log  # noqa: E402
from midas_cli.session.reader import Session  # noqa: E402

PY = sys.executable
EMHT_RATE, FPS_RATE = 220, 850  # as bench_record.py: the most each line carries
DEVICES = {"emht": f"fob://{{folder}}/emht?rate={EMHT_RATE}&sensors=4",
           "fps": f"fps://{{folder}}/fps?baud=500000&rate={FPS_RATE}&channels=9"}
GOAL_RAW_P99_MS, GOAL_FITTED_P99_MS = 1.5, 0.5
PAPER_MEAN_MS = {"emht": 43.3, "fps": 12.97}  # Appendix A.1, Table "latencies": source-to-disk means
TAIL_MAX = 20  # cycles the trakSTAR may send after the recorder stopped reading
PRIORITY_NICE = -10  # the emulators' niceness, and the recorder's in the "loaded, prioritised" condition
# name -> (busy-loop processes (None: --load), the recorder's niceness, `record --priority`)
CONDITIONS = {"idle": (0, 0, "normal"), "loaded": (None, 0, "normal"),
              "loaded-recorder-nice": (None, PRIORITY_NICE, "normal"), "loaded-workers-high": (None, 0, "high")}


def set_niceness(nice: int) -> int:
    """Set this process's niceness to ``nice`` where permitted (below the current one needs the right to);
    returns the niceness in force."""
    try:
        os.nice(nice - os.nice(0))
    except PermissionError:
        pass
    return os.nice(0)


def serve_emulator(kind: str, folder: str, stop: Any) -> None:
    """Child process: serve one emulator with its send log until ``stop`` is set."""
    from midas_cli.devices.fps.emulator import FpsEmulator, FpsEmulatorConfig
    from midas_cli.devices.trakstar.emulator import EmulatorConfig, TrakstarEmulator

    set_niceness(PRIORITY_NICE)
    log = f"{folder}/{kind}.sendlog"
    if kind == "emht":
        emulator: Any = TrakstarEmulator(EmulatorConfig(link=f"{folder}/emht", send_log=log))
    else:
        emulator = FpsEmulator(FpsEmulatorConfig(link=Path(folder) / "fps", send_log=log, keep_samples=False))
    emulator.serve_for(None, stop.is_set)
    emulator.stop()


def start_emulators(folder: Path, kinds: tuple[str, ...] = tuple(DEVICES)) -> tuple[list[mp.Process], Any]:
    context = mp.get_context("spawn")
    stop = context.Event()
    procs = [context.Process(target=serve_emulator, args=(kind, str(folder), stop)) for kind in kinds]
    for proc in procs:
        proc.start()
    deadline = time.monotonic() + 30
    while not all((folder / kind).exists() for kind in kinds):
        if time.monotonic() > deadline or not all(p.is_alive() for p in procs):
            raise RuntimeError("the emulators did not start within 30 s")
        time.sleep(0.05)
    return procs, stop


def stop_emulators(procs: list[mp.Process], stop: Any) -> None:
    stop.set()
    for proc in procs:
        proc.join(timeout=20)


def bare_reader(link: str, seconds: float, out: str) -> None:
    """Child process at niceness 0: the least a reader does (select, os.read, stamp every pedal line at the
    read that completed it; no midas); saves (seq, stamp monotonic ns) rows to ``out``."""
    set_niceness(0)
    fd = os.open(link, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    os.write(fd, encode_command("RATE", FPS_RATE) + encode_command("START"))
    decoder, stamped = LineDecoder(), []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if select.select([fd], [], [], 0.005)[0]:
            data = os.read(fd, 4096)
            now = time.monotonic_ns()
            stamped += [(m.seq, now) for m in decoder.feed(data) if isinstance(m, Sample)]
    os.write(fd, encode_command("STOP"))
    os.close(fd)
    np.save(out, np.array(stamped, dtype=np.int64).reshape(-1, 2))


def bare_reference(folder: Path, seconds: float) -> dict[str, Any]:
    """The pedal board read by :func:`bare_reader` for ``seconds``: its stamps' error, as for midas's rows."""
    folder.mkdir()
    procs, stop = start_emulators(folder, ("fps",))
    try:
        reader = mp.get_context("spawn").Process(target=bare_reader, args=(str(folder / "fps"), seconds,
                                                                          str(folder / "bare.npy")))
        reader.start()
        reader.join(timeout=seconds + 60)
    finally:
        stop_emulators(procs, stop)
    stamped = np.load(folder / "bare.npy")
    log = read_send_log(folder / "fps.sendlog")
    index = match_fps(np.rec.fromarrays([stamped[:, 0]], names="seq"), log)
    return {"rows": len(stamped), "raw": error_figures(stamped[:, 1] - log["t_out_ns"][index])}


def start_load(processes: int) -> list[subprocess.Popen]:
    """Busy loops, one per process: the cores are shared with work that never sleeps."""
    return [subprocess.Popen([PY, "-c", "while True: pass"], preexec_fn=lambda: set_niceness(0))
            for _ in range(processes)]


def record(folder: Path, duration_s: float, nice: int, priority: str) -> Path:
    """`midas record --priority PRIORITY` of both emulators for ``duration_s`` at niceness ``nice``; the
    session's path."""
    args = [arg for name, url in DEVICES.items() for arg in ("--device", f"{name}={url.format(folder=folder)}")]
    done = subprocess.run([PY, "-m", "midas_cli", "record", *args, "--duration", str(duration_s), "--out",
                           str(folder / "s"), "--subject", "1", "--task", "bench", "--trial", "1", "--no-tui",
                           "--priority", priority],
                          capture_output=True, text=True, timeout=duration_s + 120,
                          preexec_fn=lambda: set_niceness(nice))
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
    """mean and sd (signed), p50, p99 and max of |error|, in ms."""
    ms = error_ns.astype(np.float64) / 1e6
    magnitude = np.abs(ms)
    p50, p99 = np.percentile(magnitude, [50, 99])
    return {"mean_ms": round(float(ms.mean()), 4), "sd_ms": round(float(ms.std()), 4), "p50_ms": round(float(p50), 4),
            "p99_ms": round(float(p99), 4), "max_ms": round(float(magnitude.max()), 4)}


def stream_errors(session: Session, name: str, log: dict[str, np.ndarray], anchor_ns: int) -> dict[str, Any]:
    """Raw and fitted error of one stream's rows against the emulator's send times."""
    table = session.read_columns(name)
    index = (match_fps if name == "fps" else match_emht)(table, log)
    out_ns = log["t_out_ns"][index] + anchor_ns
    spec = session.stream_spec(name)
    fit = fit_stream(table, spec.columns, spec.nominal_rate_hz)
    if fit is None or not fit.fitted_samples:
        raise ValueError(f"{name}: the clock fit found nothing to fit")
    due_ns = log["t_due_ns"][index] + anchor_ns
    against_due = fit.fitted_ns - due_ns
    return {"rows": len(table), "sent": len(log["t_out_ns"]), "clock": fit.clock, "drift_ppm": round(fit.drift_ppm, 2),
            "raw": error_figures(table["t_host_ns"] - out_ns), "fitted": error_figures(fit.fitted_ns - out_ns),
            "fitted_vs_due_less_mean": error_figures(against_due - int(round(against_due.mean()))),
            "emulator_late": error_figures(out_ns - due_ns)}


def run_condition(name: str, load_processes: int, nice: int, priority: str, duration_s: float,
                  bare_s: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="midas-bench-ts-") as tmp:
        folder = Path(tmp)
        load = start_load(load_processes)
        try:
            time.sleep(2.0 if load_processes else 0.0)  # let the load average see the busy loops start
            load_before = load_average()
            procs, stop = start_emulators(folder)
            try:
                session_path = record(folder, duration_s, nice, priority)
            finally:
                stop_emulators(procs, stop)
            bare = bare_reference(folder / "bare", bare_s)
            load_after = load_average()
        finally:
            for proc in load:
                proc.kill()
                proc.wait()
        manifest = json.loads((session_path / "manifest.json").read_text(encoding="utf-8"))
        missing = check_matchable(manifest)
        session = Session.open(session_path)
        streams = {name: {**stream_errors(session, name, read_send_log(folder / f"{name}.sendlog"),
                                          manifest["clock"]["anchor_ns"]), "missing": missing[name]}
                   for name in DEVICES}
    workers = {device: manifest["devices"][device].get("priority") for device in DEVICES}  # read back in each worker
    return {"condition": name, "load_processes": load_processes, "recorder_nice": nice, "priority": priority,
            "worker_priority": workers, "duration_s": duration_s,
            "load_average_before_after": [load_before, load_after], "streams": streams, "bare_fps_reader": bare}


def check_matchable(manifest: dict[str, Any]) -> dict[str, int]:
    """Matching rows to records needs one connection per device and, for the trakSTAR (matched by order),
    every cycle decoded. Pedal samples the board never got onto the line (its transmit buffer full while
    the host did not read) are matched around; returns their count per stream."""
    missing = {}
    for name in DEVICES:
        entry = manifest["streams"][name]
        missing[name] = entry["seq_gaps"]["missing"]
        if name == "emht" and (entry["corrupt"] or entry["seq_gaps"]["missing"] or entry["dropped"]):
            raise RuntimeError(f"{name}: records were lost ({entry['corrupt']} corrupt, "
                               f"{entry['seq_gaps']['missing']} missing): the rows cannot be matched by order")
        if sum(e["event"] == "opened" for e in manifest["devices"][name]["events"]) != 1:
            raise RuntimeError(f"{name}: the device reconnected during the recording")
    return missing


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="8 s per condition (smoke run)")
    parser.add_argument("--duration", type=float, default=40.0, help="seconds of recording per condition")
    parser.add_argument("--load", type=int, default=2, help="busy-loop processes in the loaded conditions")
    parser.add_argument("--conditions", default=",".join(CONDITIONS),
                        help=f"comma-separated, of {', '.join(CONDITIONS)} (default: all)")
    parser.add_argument("--name", default="timestamp_error", help="the result's name: results/NAME.json")
    args = parser.parse_args()
    names = [name for name in args.conditions.split(",") if name]
    if not args.name.replace("_", "").replace("-", "").isalnum():
        parser.error(f"--name must be letters, digits, '_' and '-', got {args.name!r}")
    unknown = sorted(set(names) - set(CONDITIONS))
    if unknown:
        parser.error(f"unknown condition(s) {', '.join(unknown)}; known: {', '.join(CONDITIONS)}")
    duration = 8.0 if args.quick else args.duration
    bare_s = 4.0 if args.quick else 15.0
    prioritised = set_niceness(PRIORITY_NICE)  # where permitted; the recorder and the load are started at 0
    conditions = []
    for name in names:
        load, nice, priority = CONDITIONS[name]
        if nice < 0 and prioritised != PRIORITY_NICE:
            continue  # the recorder cannot be started at nice -10 without the right to
        conditions.append(run_condition(name, args.load if load is None else load, nice, priority, duration, bare_s))
    write_result(args.name, {
        "machine": machine_info(), "quick": args.quick, "cores": len(os.sched_getaffinity(0)),
        "emulator_nice": prioritised,
        "devices": [url.format(folder="$TMP") for url in DEVICES.values()], "goal_raw_p99_ms": GOAL_RAW_P99_MS,
        "goal_fitted_p99_ms": GOAL_FITTED_P99_MS, "paper_mean_ms": PAPER_MEAN_MS, "conditions": conditions})


if __name__ == "__main__":
    main()
