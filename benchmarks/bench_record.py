"""Recording latency, loss, CPU and bytes/min with every device at full rate on emulators.

Runs the real CLI (`python -m midas_cli record`) against `midas emulate trakstar` (fob://, 4 sensors x
220 Hz over 115200 baud, the most that line carries: 4 x 240 Hz needs 124.8 kbit/s) and
`midas emulate fps` (9 channels at 850 Hz, the most 500000 baud carries),
plus `sim://video?rate=30` and `sim://handkp?rate=30`, at two durations. Then a short in-process run
splits each batch's latency, inside its device worker (which writes its own rows), into "read -> the
write starts" and "write", and measures the bookkeeping hop to the recorder that follows (profile).

    .venv/bin/python benchmarks/bench_record.py            # 10 s and 30 s  -> results/record.json
    .venv/bin/python benchmarks/bench_record.py --quick    # 5 s smoke run
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load_average, machine_info, write_result  # noqa: E402
from process_cpu import percent_between, snapshot  # noqa: E402

PY = sys.executable
EMHT_RATE, FPS_RATE = 220, 850  # 220 Hz: the most 4 sensors x 13-byte records carry at 115200 baud
PAPER_MEAN_MS = {"emht": 43.3, "depth (handkp)": 24.66, "fps": 12.97}


def device_args(folder: Path) -> list[str]:
    return ["--device", f"emht=fob://{folder}/ts?rate={EMHT_RATE}&sensors=4",
            "--device", f"fps=fps://{folder}/fps?baud=500000&rate={FPS_RATE}&channels=9",
            "--device", "video=sim://video?rate=30", "--device", "handkp=sim://handkp?rate=30"]


def start_emulators(folder: Path) -> list[subprocess.Popen]:
    procs = []
    for kind, link in (("trakstar", "ts"), ("fps", "fps")):
        procs.append(subprocess.Popen([PY, "-m", "midas_cli", "emulate", kind, "--link", str(folder / link),
                                       "--summary", str(folder / f"{link}.json"), "--json"],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    deadline = time.monotonic() + 30
    while not all((folder / n).exists() for n in ("ts", "fps")):
        if time.monotonic() > deadline:
            raise RuntimeError("emulators did not start within 30 s")
        time.sleep(0.1)
    return procs


def stop_emulators(procs: list[subprocess.Popen], folder: Path) -> dict:
    for p in procs:
        p.send_signal(signal.SIGINT)
    for p in procs:
        p.wait(timeout=20)
    return {"emht": json.loads((folder / "ts.json").read_text()), "fps": json.loads((folder / "fps.json").read_text())}


def run_record(duration_s: float) -> dict:
    """One CLI recording at full rate; returns manifest figures, loss vs emulators, CPU."""
    with tempfile.TemporaryDirectory(prefix="midas-bench-rec-") as tmp:
        folder = Path(tmp)
        emulators = start_emulators(folder)
        load_before = load_average()
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.monotonic()
        proc = subprocess.Popen([PY, "-m", "midas_cli", "record", *device_args(folder), "--duration", str(duration_s),
                                 "--out", str(folder / "s"), "--subject", "1", "--task", "bench", "--trial", "1",
                                 "--no-tui"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        steady = steady_state_cpu(proc, duration_s)
        stdout, stderr = proc.communicate()
        proc = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
        wall = time.monotonic() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        summaries = stop_emulators(emulators, folder)
        if proc.returncode != 0:
            raise RuntimeError(f"midas record failed ({proc.returncode}): {proc.stderr[-2000:]}")
        session = Path(proc.stdout.strip().splitlines()[-1])
        manifest = json.loads((session / "manifest.json").read_text())
    cpu_s = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"duration_s": duration_s, "wall_s": round(wall, 2), "load_average_before_after": [load_before, load_average()],
            "recorder_cpu_s": round(cpu_s, 2), "recorder_cpu_percent_of_one_core": round(100 * cpu_s / wall, 1),
            "cpu_note": "recorder + its worker processes (RUSAGE_CHILDREN), including ~2 s Python start-up",
            "steady_cpu_percent_of_one_core": steady,
            "streams": {name: stream_figures(name, entry, summaries) for name, entry in manifest["streams"].items()
                        if name != "events"}}  # the operator's markers: none in a benchmark


def steady_state_cpu(proc: subprocess.Popen, duration_s: float) -> dict:
    """CPU per process (recorder, each worker) over the middle of the recording: from 40 % of --duration
    (the devices open and streaming) to 90 % (before the stop), as % of one core."""
    t_start = time.monotonic()
    time.sleep(0.4 * duration_s)
    before, t_before = snapshot(proc.pid), time.monotonic()
    time.sleep(max(0.0, 0.9 * duration_s - (t_before - t_start)))
    after, t_after = snapshot(proc.pid), time.monotonic()
    return {"window_s": round(t_after - t_before, 2), "percent": percent_between(before, after, t_after - t_before)}


def stream_figures(name: str, entry: dict, summaries: dict) -> dict:
    span_min = (entry["last_t_host_ns"] - entry["first_t_host_ns"]) / 60e9
    figures = {"samples": entry["samples"], "measured_rate_hz": entry["measured_rate_hz"],
               "latency_ms": {k: entry["latency_ms"][k] for k in ("p50", "p95", "p99", "max")},
               "seq_gaps_missing": entry["seq_gaps"]["missing"], "queue_dropped": entry["dropped"],
               "corrupt": entry["corrupt"], "missing_unexplained": entry["missing_unexplained_live"],
               "bytes": entry["bytes"], "bytes_per_minute": round(entry["bytes"] / span_min) if span_min else None}
    if name == "emht":
        s = summaries["emht"]
        figures["emulator_sent"] = s["stream_groups_sent"]
        figures["emulator_skipped"] = s["cycles_skipped_line_full"] + s["cycles_skipped_stall"]
    elif name == "fps":
        s = summaries["fps"]
        figures["emulator_sent"] = s["sent"]
        figures["emulator_skipped"] = s["skipped"]["stall"] + s["skipped"]["tx_full"]
    if "emulator_sent" in figures:
        figures["sent_minus_recorded"] = figures["emulator_sent"] - entry["samples"]
    return figures


def profile_stages(duration_s: float) -> dict:
    """In-process Recorder whose bookkeeping thread also stamps each message's arrival. Each worker
    writes its rows itself, and its message carries the rows' commit times and the write's duration,
    so each row's latency splits into (read -> the worker's write starts) and (write); the hop to the
    recorder (committed -> received) comes after the rows are on disk and is no part of the latency."""
    from midas_cli.record.recorder import Recorder, RecordPlan
    from midas_cli.session.writer import SessionMetadata

    class StampingRecorder(Recorder):
        def __init__(self, plan: RecordPlan) -> None:
            super().__init__(plan)
            self.stamps: list[tuple] = []

        def _account(self, batch):  # noqa: ANN001 - same signature as Recorder._account
            received = self.clock.now_ns()
            super()._account(batch)
            self.stamps.append((batch.stream, received, batch.committed_ns, batch.write_ns, batch.t_host_ns))

    with tempfile.TemporaryDirectory(prefix="midas-bench-prof-") as tmp:
        folder = Path(tmp)
        emulators = start_emulators(folder)
        urls = dict(a.split("=", 1) for a in device_args(folder)[1::2])
        recorder = StampingRecorder(RecordPlan(SessionMetadata("1", "bench", 1), urls, folder / "s"))
        recorder.start()
        recorder.wait_ready()
        display = threading.Thread(target=_display_like_load, args=(recorder, duration_s), daemon=True)
        display.start()
        display.join()
        recorder.stop()
        stop_emulators(emulators, folder)
    return summarise_stamps(recorder.stamps)


def _with_emulators(body):  # noqa: ANN001, ANN202
    with tempfile.TemporaryDirectory(prefix="midas-bench-win-") as tmp:
        emulators = start_emulators(Path(tmp))
        try:
            return body(dict(a.split("=", 1) for a in device_args(Path(tmp))[1::2]))
        finally:
            stop_emulators(emulators, Path(tmp))


def _display_like_load(recorder, duration_s: float) -> None:
    """What `midas record --no-tui` does in the main thread: a snapshot every 0.25 s."""
    end = time.monotonic() + duration_s
    while time.monotonic() < end:
        recorder.snapshot(duration_s)
        time.sleep(0.25)


def summarise_stamps(stamps: list) -> dict:
    """Per stream, from (stream, received_ns, committed_ns[rows], write_ns, t_host_ns[rows]) stamps.
    ``read_to_writer_thread_ms``: a row's read -> its worker's write starts (the worker is the writer
    now; the key keeps report.py's name); ``write_ms``: one append (the mean over a message's appends);
    ``read_to_committed_ms``: the
    recorded latency; ``committed_to_recorder_ms``: the bookkeeping hop, after the rows are on disk."""
    result = {}
    for stream in sorted({s[0] for s in stamps}):
        rows = [s for s in stamps if s[0] == stream]
        # a message gathers the appends of up to 50 ms (record/worker.py BOOKKEEPING_EVERY_S); the rows of
        # one append share its commit time, so appends = distinct commit times, each taking the mean write
        appends = [max(1, len(np.unique(r[2]))) for r in rows]
        to_write = np.concatenate([(r[2] - r[3] / n - r[4]) / 1e6 for r, n in zip(rows, appends)])
        latency = np.concatenate([(r[2] - r[4]) / 1e6 for r in rows])
        write = np.array([r[3] / n / 1e6 for r, n in zip(rows, appends)])
        hop = np.array([(r[1] - int(r[2][-1])) / 1e6 for r in rows])
        spread = np.array([(r[4][-1] - r[4][0]) / 1e6 for r in rows])
        sizes = np.array([len(r[4]) for r in rows])
        result[stream] = {"batches": len(rows), "rows_per_batch_mean": round(float(sizes.mean()), 2),
                          "read_to_writer_thread_ms": _percentiles(to_write), "write_ms": _percentiles(write),
                          "read_to_committed_ms": _percentiles(latency),
                          "committed_to_recorder_ms": _percentiles(hop),
                          "rows_spread_within_batch_ms": _percentiles(spread)}
    return result


def pump_window(urls: dict[str, str], seconds: float) -> dict:
    """Each device alone, in this process, through the worker's own read/write loop (record/worker.py
    ``_pump``, appending to scratch stream files) with a queue that only stamps: latency from a row's
    host read to its append returning, i.e. the whole recorded latency without the other devices."""
    from midas_cli.clock import HostClock
    from midas_cli.devices.registry import DeviceContext, create_device
    from midas_cli.record.worker import WorkerJob, WorkerOutput, _pump

    result: dict = {"flush": "rows written by the worker as soon as a read returns them"}
    with tempfile.TemporaryDirectory(prefix="midas-bench-pump-") as tmp:
        for name, url in urls.items():
            clock = HostClock.anchored_now()
            device = create_device(name, url, DeviceContext(clock, clock.now_ns(), 0))
            files = {spec.name: Path(tmp) / f"{spec.name}.csv" for spec in device.streams}
            for spec in device.streams:
                files[spec.name].write_text(spec.header_line())
            output = WorkerOutput(name, _StampQueue(), clock)
            output.open({stream: str(path) for stream, path in files.items()})
            device.open()
            stop = threading.Event()
            threading.Timer(seconds, stop.set).start()
            job = WorkerJob(name, url, clock.anchor_ns, clock.now_ns(), 0, 5.0, os.getppid())
            try:
                _pump(device, job, output, stop)
            finally:
                device.close()
                output.close()
            latencies = output.out.latencies_ms
            result[name] = _percentiles(np.concatenate(latencies)) if latencies else None
    return result


class _StampQueue:
    """Stands in for the worker's mp.Queue: keeps each row's commit time minus its host read time."""

    def __init__(self) -> None:
        self.latencies_ms: list[np.ndarray] = []

    def put_nowait(self, batch) -> None:  # noqa: ANN001
        self.latencies_ms.append((batch.committed_ns - batch.t_host_ns) / 1e6)


def queue_transit(rate_hz: float, seconds: float, rows: int) -> dict:
    """A spawned process puts DataBatch messages (``rows`` rows each) on an mp.Queue at ``rate_hz``;
    the parent's get() time minus the put time: the bookkeeping hop's own cost (no longer part of the
    recorded latency: the rows are on disk before their message is put)."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    q = ctx.Queue(maxsize=4096)
    child = ctx.Process(target=_put_batches, args=(q, rate_hz, seconds, rows), daemon=True)
    child.start()
    transit = []
    while True:
        message = q.get(timeout=30)
        if message is None:
            break
        transit.append((time.time_ns() - int(message.t_host_ns[-1])) / 1e6)
    child.join()
    return {"rate_hz": rate_hz, "rows_per_batch": rows, **_percentiles(np.array(transit[int(rate_hz):]))}


def _put_batches(q, rate_hz: float, seconds: float, rows: int) -> None:  # noqa: ANN001
    from midas_cli.record.messages import DataBatch

    end = time.monotonic() + seconds
    while time.monotonic() < end:
        seq, now = np.arange(rows, dtype=np.int64), np.full(rows, time.time_ns(), dtype=np.int64)
        q.put(DataBatch("fps", "fps", seq, now, now, (1, 2), 75 * rows, 50_000, 0))
        time.sleep(1.0 / rate_hz)
    q.put(None)


def _percentiles(values: np.ndarray) -> dict:
    return {"p50": round(float(np.percentile(values, 50)), 3), "p95": round(float(np.percentile(values, 95)), 3),
            "p99": round(float(np.percentile(values, 99)), 3), "max": round(float(values.max()), 3),
            "n": int(len(values))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one 5 s run and a 3 s profile")
    parser.add_argument("--durations", type=float, nargs="+", default=[10.0, 30.0])
    args = parser.parse_args()
    durations = [5.0] if args.quick else args.durations
    runs = []
    for d in durations:
        print(f"record: {d:.0f} s at full rate ...", file=sys.stderr)
        runs.append(run_record(d))
    print("record: in-process stage profile ...", file=sys.stderr)
    load = load_average()
    profile = profile_stages(3.0 if args.quick else 10.0)
    print("record: worker loop and queue transit ...", file=sys.stderr)
    window = _with_emulators(lambda urls: pump_window(urls, 2.0 if args.quick else 5.0))
    transit = {"idle_parent": queue_transit(200.0, 2.0 if args.quick else 5.0, 5)}
    write_result("record", {"machine": machine_info(), "quick": args.quick, "paper_mean_ms": PAPER_MEAN_MS,
                            "devices": device_args(Path("$TMP"))[1::2], "runs": runs,
                            "stage_profile": {"load_average_before_after": [load, load_average()], "streams": profile,
                                              "worker_batch_window": window, "queue_transit_ms": transit}})


if __name__ == "__main__":
    main()
