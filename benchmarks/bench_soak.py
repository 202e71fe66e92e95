"""Soak: `midas record` at full rate on the emulators for a long time: loss, memory, latency over time.

Starts the same emulators and devices as bench_record.py (`midas emulate trakstar` 4 x 200 Hz,
`midas emulate fps` 9 channels at 850 Hz, `sim://video?rate=30`, `sim://handkp?rate=30`) and runs
`python -m midas_cli record ... --status-json --duration <minutes * 60>`. While it records, this script
reads the status line the recorder prints every second and, every few seconds, the resident memory
(VmRSS from /proc) and CPU time of the recorder, of each of its child processes (device workers,
multiprocessing's resource tracker) and of the emulators. Afterwards it cuts the run into windows
(default 30 s) and reports, per window and stream: samples, measured rate, new dropped / corrupt /
sequence-missing records, latency (the status lines' ``latency_window_ms``, p50/p99/max over about the
last 10 s, when the recorder provides it; left out otherwise), memory and CPU. At the end: the
session manifest's loss figures (sequence gaps, queue drops, emulator sent vs recorded), the memory
slope (least-squares line after a warm-up, MiB per 10 min) and each stream's per-window p99 in the
first third vs the last third of the run. Writes results/<name>.json and results/<name>.png.

    .venv/bin/python benchmarks/bench_soak.py                          # 30 min -> results/soak.json
    .venv/bin/python benchmarks/bench_soak.py --minutes 5 --name soak-short
    .venv/bin/python benchmarks/bench_soak.py --quick                     # 2 min -> results/soak-short.json
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_record import device_args, start_emulators, stop_emulators, stream_figures  # noqa: E402
from machine import RESULTS, load_average, machine_info, write_result  # noqa: E402

from midas_cli.session.reader import Session  # noqa: E402

PY = sys.executable
MIB = 1024.0  # kB per MiB (/proc reports kB = KiB)
CLK_TCK = os.sysconf("SC_CLK_TCK")
LATENCY_WINDOW_S = 10.0  # span of the status lines' latency_window_ms (recorder side)
GRACE_S = 90.0  # start-up + finalising allowed beyond --duration before the recorder is stopped


# ---- processes: tree, memory, CPU (Linux /proc) -------------------------------------------------------

def process_tree(root: int) -> list[int]:
    """``root`` and every descendant still alive (pids), parents first."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry.name))
    tree, todo = [], [root]
    while todo:
        pid = todo.pop(0)
        tree.append(pid)
        todo += sorted(children.get(pid, []))
    return tree


def rss_kib(pid: int) -> int | None:
    """Resident set size (VmRSS) of ``pid`` in KiB; None if it has exited."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def cpu_s(pid: int) -> float | None:
    """User + system CPU seconds ``pid`` has used itself (not its children); None if it has exited."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime, stime: fields 14, 15 of stat(5)


def role(pid: int, root: int) -> str:
    """What a process of the recorder's tree is, from its command line."""
    if pid == root:
        return "recorder"
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return "exited"
    return "resource_tracker" if "resource_tracker" in cmdline else "worker"


def sample_processes(recorder: int, emulators: dict[str, int], t_s: float) -> dict[str, Any]:
    """One memory/CPU sample at ``t_s`` (seconds since the recorder was launched, this script's clock)."""
    procs = {}
    for pid in process_tree(recorder):
        rss, cpu = rss_kib(pid), cpu_s(pid)
        if rss is not None:
            procs[str(pid)] = {"role": role(pid, recorder), "rss_mib": round(rss / MIB, 2), "cpu_s": cpu}
    emus = {name: rss_kib(pid) for name, pid in emulators.items()}
    return {"t_s": round(t_s, 2), "load_1min": load_average(), "processes": procs,
            "recorder_total_mib": round(sum(p["rss_mib"] for p in procs.values()), 2),
            "recorder_cpu_s": round(sum(p["cpu_s"] or 0.0 for p in procs.values()), 2),
            "emulators_mib": {n: (round(v / MIB, 2) if v is not None else None) for n, v in emus.items()},
            "emulators_cpu_s": round(sum(cpu_s(pid) or 0.0 for pid in emulators.values()), 2)}


# ---- the run ------------------------------------------------------------------------------------------

class StatusReader(threading.Thread):
    """Reads the recorder's stdout: JSON status lines (stamped on arrival) and, last, the session path."""

    def __init__(self, stream, started: float) -> None:  # noqa: ANN001 - a text pipe
        super().__init__(daemon=True)
        self.stream, self.started = stream, started
        self.statuses: list[dict[str, Any]] = []
        self.last_line = ""

    def run(self) -> None:
        for line in self.stream:
            line = line.strip()
            if line.startswith("{"):
                status = json.loads(line)
                status["t_s"] = time.monotonic() - self.started
                self.statuses.append(status)
            elif line:
                self.last_line = line


def record_soak(folder: Path, duration_s: float, sample_s: float) -> dict[str, Any]:
    """Run the recorder for ``duration_s`` against emulators in ``folder``; statuses, samples, manifest."""
    emulators = start_emulators(folder)
    stderr = (folder / "record.stderr").open("w")
    started = time.monotonic()
    proc = subprocess.Popen([PY, "-m", "midas_cli", "record", *device_args(folder), "--duration", str(duration_s),
                             "--out", str(folder / "s"), "--subject", "1", "--task", "soak", "--trial", "1",
                             "--status-json"], stdout=subprocess.PIPE, stderr=stderr, text=True, bufsize=1)
    reader = StatusReader(proc.stdout, started)
    reader.start()
    samples, overdue = [], started + duration_s + GRACE_S
    emulator_pids = {"trakstar": emulators[0].pid, "fps": emulators[1].pid}
    try:
        while proc.poll() is None and time.monotonic() < overdue:
            samples.append(sample_processes(proc.pid, emulator_pids, time.monotonic() - started))
            _sleep_unless_exited(proc, sample_s)
    finally:
        _stop_if_running(proc)
        reader.join(timeout=30)
        wall = time.monotonic() - started
        _stop_emulators_patiently(emulators)
    summaries = stop_emulators(emulators, folder)
    stderr.close()
    if proc.returncode != 0 or not reader.statuses:
        tail = (folder / "record.stderr").read_text(errors="replace")[-2000:]
        raise RuntimeError(f"midas record failed (exit {proc.returncode}, {len(reader.statuses)} status lines, "
                           f"{wall:.0f} s for a {duration_s:.0f} s recording): {tail}")
    return {"statuses": reader.statuses, "samples": samples, "wall_s": round(wall, 1), "summaries": summaries,
            "session": Path(reader.last_line)}


def _sleep_unless_exited(proc: subprocess.Popen, seconds: float) -> None:
    try:
        proc.wait(timeout=seconds)
    except subprocess.TimeoutExpired:
        pass


def _stop_emulators_patiently(emulators: list[subprocess.Popen]) -> None:
    """SIGINT and wait up to 5 min: with --summary the FPS emulator keeps every sample it sent and writes
    them all at exit (about 180 MB of JSON after 30 min), longer than stop_emulators' 20 s on a loaded
    machine; stop_emulators then only reads the summaries (signalling an exited Popen does nothing)."""
    for proc in emulators:
        proc.send_signal(signal.SIGINT)
    for proc in emulators:
        proc.wait(timeout=300)


def _stop_if_running(proc: subprocess.Popen) -> None:
    """A recorder still running past its duration + GRACE_S: SIGINT (it finalises), then SIGKILL."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


# ---- analysis (pure functions of the statuses and samples) ---------------------------------------------

def stream_states(status: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """stream name -> its status object, with the device's reconnect count and state added."""
    return {s["name"]: {**s, "reconnects": d["reconnects"], "state": d["state"]}
            for d in status["devices"] for s in d["streams"]}


def window_bounds(statuses: list[dict], window_s: float) -> Iterator[tuple[int, int]]:
    """(first, last) status index of each consecutive window of ``window_s`` seconds of recording
    (``elapsed_s``, the recorder's clock); each window's counts run from the previous window's last status."""
    elapsed = np.array([s["elapsed_s"] for s in statuses])
    edges = np.arange(window_s, elapsed[-1] + 1e-9, window_s)
    prev = 0
    for edge in edges:
        last = int(np.searchsorted(elapsed, edge, side="right")) - 1
        if last > prev:
            yield prev, last
            prev = last


def window_latency(statuses: list[dict], stream: str) -> dict[str, Any] | None:
    """Latency over a window from the status lines' ``latency_window_ms`` (each over ~10 s): lines taken
    every 10 s so their spans do not overlap; p99 and max are the largest, p50 the median, n the sum.
    None when the recorder does not report it."""
    picked, next_t = [], -np.inf
    for status in statuses:
        lat = stream_states(status).get(stream, {}).get("latency_window_ms")
        if lat and lat.get("n") and status["elapsed_s"] >= next_t:
            picked.append(lat)
            next_t = status["elapsed_s"] + LATENCY_WINDOW_S
    if not picked:
        return None
    return {"p50": round(float(np.median([p["p50"] for p in picked])), 3),
            "p99": round(float(max(p["p99"] for p in picked)), 3),
            "max": round(float(max(p["max"] for p in picked)), 3), "n": int(sum(p["n"] for p in picked)),
            "spans": len(picked)}


def window_streams(statuses: list[dict], first: int, last: int) -> dict[str, dict[str, Any]]:
    """Per stream over statuses[first..last]: new samples, rate, new losses, latency."""
    a, b = stream_states(statuses[first]), stream_states(statuses[last])
    span = statuses[last]["elapsed_s"] - statuses[first]["elapsed_s"]
    out = {}
    for name, end in b.items():
        start = a.get(name, {})
        delta = {k: end[k] - start.get(k, 0) for k in ("samples", "dropped", "corrupt", "seq_missing", "reconnects")}
        out[name] = {**delta, "rate_hz": round(delta["samples"] / span, 3) if span > 0 else None,
                     "status_rate_hz": end["measured_rate_hz"], "state": end["state"]}
        latency = window_latency(statuses[first + 1:last + 1], name)
        if latency is not None:
            out[name]["latency_ms"] = latency
    return out


def window_memory(samples: list[dict], t0: float, t1: float) -> dict[str, Any] | None:
    """Recorder-tree memory (mean/max MiB), CPU (% of one core) and emulator memory between t0 and t1
    (seconds since launch, this script's clock)."""
    inside = [s for s in samples if t0 <= s["t_s"] <= t1]
    if len(inside) < 2:
        return None
    total = [s["recorder_total_mib"] for s in inside]
    span = inside[-1]["t_s"] - inside[0]["t_s"]
    emulators = {n: round(float(np.mean([s["emulators_mib"][n] or 0 for s in inside])), 2)
                 for n in inside[0]["emulators_mib"]}
    return {"recorder_mean_mib": round(float(np.mean(total)), 2), "recorder_max_mib": round(max(total), 2),
            "recorder_cpu_percent": _cpu_percent(inside, "recorder_cpu_s", span),
            "emulators_cpu_percent": _cpu_percent(inside, "emulators_cpu_s", span),
            "emulators_mean_mib": emulators, "load_1min": inside[-1]["load_1min"]}


def _cpu_percent(inside: list[dict], key: str, span_s: float) -> float:
    """CPU use over the samples, % of one core (a process that exited takes its CPU time with it: >= 0)."""
    return round(100 * max(inside[-1][key] - inside[0][key], 0.0) / span_s, 1)


def windows(statuses: list[dict], samples: list[dict], window_s: float) -> list[dict[str, Any]]:
    """The run cut into windows of ``window_s`` seconds of recording: streams, memory, CPU, load."""
    out = []
    for first, last in window_bounds(statuses, window_s):
        t0, t1 = statuses[first]["t_s"], statuses[last]["t_s"]
        out.append({"start_s": round(statuses[first]["elapsed_s"], 1), "end_s": round(statuses[last]["elapsed_s"], 1),
                    "streams": window_streams(statuses, first, last), "memory": window_memory(samples, t0, t1)})
    return out


def slope_mib_per_10min(t_s: np.ndarray, mib: np.ndarray) -> float | None:
    """Least-squares slope of memory over time, MiB per 10 minutes (None with fewer than 3 points)."""
    if len(t_s) < 3 or np.ptp(t_s) <= 0:
        return None
    return round(float(np.polyfit(t_s / 600.0, mib, 1)[0]), 3)


def memory_summary(samples: list[dict], start_s: float, end_s: float, warmup_s: float) -> dict[str, Any]:
    """Memory from the end of the warm-up to the end of the recording: start/end/slope for the recorder
    tree, each of its processes and each emulator. ``start_s``/``end_s``: the first and the last status
    line of the recording (seconds since launch; finalising, after the last one, is left out)."""
    kept = [s for s in samples if start_s + warmup_s <= s["t_s"] <= end_s]
    t = np.array([s["t_s"] for s in kept])

    def series(values: list[float | None]) -> dict[str, Any]:
        v = np.array([np.nan if x is None else x for x in values], dtype=float)
        ok = np.isfinite(v)
        return {"start_mib": _first(v[ok]), "end_mib": _first(v[ok][::-1]), "max_mib": _max(v[ok]),
                "slope_mib_per_10min": slope_mib_per_10min(t[ok], v[ok])}

    pids = sorted({pid for s in kept for pid in s["processes"]}, key=int)
    return {"warmup_s": warmup_s, "samples": len(kept),
            "recorder_total": series([s["recorder_total_mib"] for s in kept]),
            "processes": {pid: {"role": next(s["processes"][pid]["role"] for s in kept if pid in s["processes"]),
                                **series([s["processes"].get(pid, {}).get("rss_mib") for s in kept])}
                          for pid in pids},
            "emulators": {n: series([s["emulators_mib"][n] for s in kept]) for n in (kept[0]["emulators_mib"]
                                                                                    if kept else {})}}


def _first(v: np.ndarray) -> float | None:
    return round(float(v[0]), 2) if len(v) else None


def _max(v: np.ndarray) -> float | None:
    return round(float(v.max()), 2) if len(v) else None


def latency_stability(wins: list[dict]) -> dict[str, Any]:
    """Per stream: the windows' p99 (ms), median over the first third vs the last third of the run, and
    the largest; empty when no window has latency."""
    out = {}
    names = sorted({n for w in wins for n, s in w["streams"].items() if "latency_ms" in s})
    third = max(len(wins) // 3, 1)
    for name in names:
        p99 = [w["streams"][name]["latency_ms"]["p99"] for w in wins if "latency_ms" in w["streams"].get(name, {})]
        if len(p99) >= 2:
            first, last = float(np.median(p99[:third])), float(np.median(p99[-third:]))
            out[name] = {"windows": len(p99), "p99_first_third_ms": round(first, 3),
                         "p99_last_third_ms": round(last, 3), "p99_max_window_ms": round(max(p99), 3),
                         "last_over_first": round(last / first, 3) if first > 0 else None}
    return out


# ---- plot ---------------------------------------------------------------------------------------------

def plot(result: dict[str, Any], samples: list[dict], path: Path) -> None:
    """Three panels against minutes of recording: resident memory of the recorder tree (sum), of each of
    its processes and of the emulators; the same as change since the warm-up ended; per-window p99."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    start = result["recording_start_s"]
    samples = [s for s in samples if start <= s["t_s"] <= result["recording_end_s"]]
    t = np.array([s["t_s"] - start for s in samples]) / 60.0
    series = {"recorder + children (sum)": [s["recorder_total_mib"] for s in samples]}
    series.update({f"{info['role']} {pid}": [s["processes"].get(pid, {}).get("rss_mib", np.nan) for s in samples]
                   for pid, info in result["memory"]["processes"].items()})
    series.update({f"emulator {n}": [s["emulators_mib"][n] or np.nan for s in samples] for n in samples[0]["emulators_mib"]})
    fig, (mem, grow, lat) = plt.subplots(3, 1, figsize=(9, 10), sharex=True)
    warm = t >= result["memory"]["warmup_s"] / 60.0
    for label, values in series.items():
        v = np.array(values, dtype=float)
        style = {"lw": 2} if label.startswith("recorder +") else ({"ls": "--", "lw": 1} if "emulator" in label else {"lw": 1})
        mem.plot(t, v, label=label, **style)
        if warm.any():
            grow.plot(t[warm], v[warm] - v[warm][0], label=label, **style)
    for ax, ylabel in ((mem, "resident memory (MiB)"), (grow, "change since the warm-up (MiB)")):
        ax.axvline(result["memory"]["warmup_s"] / 60.0, color="grey", ls=":", lw=1)
        ax.set_ylabel(ylabel)
    mem.legend(fontsize=7, ncol=2)
    _plot_latency(lat, result)
    lat.set_xlabel("minutes since the recording started")
    fig.suptitle(f"midas record soak, {result['minutes']:g} min at full rate ({result['machine']['date_utc']})")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_latency(ax, result: dict[str, Any]) -> None:  # noqa: ANN001 - a matplotlib Axes
    wins = result["windows"]
    plotted = False
    for name in sorted({n for w in wins for n in w["streams"]}):
        pts = [((w["end_s"]) / 60.0, w["streams"][name]["latency_ms"]["p99"]) for w in wins
               if "latency_ms" in w["streams"].get(name, {})]
        if pts:
            ax.plot(*zip(*pts), marker="o", ms=3, label=name)
            plotted = True
    if plotted:
        ax.axhline(5.0, color="grey", ls=":", lw=1)
        ax.set_yscale("log")
        ax.set_ylabel(f"p99 latency per {result['window_s']:g} s window (ms, log)")
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "the recorder's status lines carry no latency_window_ms: no latency over time",
                ha="center", va="center", transform=ax.transAxes)


# ---- main ---------------------------------------------------------------------------------------------

def soak(minutes: float, window_s: float, sample_s: float, warmup_s: float) -> tuple[dict[str, Any], list[dict]]:
    """The whole soak: record, then summarise; returns the result and the raw memory samples."""
    load_before = load_average()
    with tempfile.TemporaryDirectory(prefix="midas-bench-soak-") as tmp:
        run = record_soak(Path(tmp), minutes * 60.0, sample_s)
        manifest = Session.open(run["session"]).manifest
    statuses, samples = run["statuses"], run["samples"]
    wins = windows(statuses, samples, window_s)
    start, end = statuses[0]["t_s"], next(s["t_s"] for s in reversed(statuses) if not s.get("stopping"))
    result = {"machine": machine_info(), "minutes": minutes, "window_s": window_s, "sample_s": sample_s,
              "devices": device_args(Path("$TMP"))[1::2], "wall_s": run["wall_s"],
              "load_average_before_after": [load_before, load_average()], "recording_start_s": round(start, 2),
              "recording_end_s": round(end, 2),
              "status_lines": len(statuses),
              "latency_window_reported": any("latency_ms" in s for w in wins for s in w["streams"].values()),
              "streams": {n: stream_figures(n, e, run["summaries"]) if e["samples"] else {"samples": 0}
                          for n, e in manifest["streams"].items()},
              "session_status": manifest["status"], "memory": memory_summary(samples, start, end, warmup_s),
              "latency_stability": latency_stability(wins), "windows": wins}
    return result, samples


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=30.0, help="recording length (default 30)")
    parser.add_argument("--quick", action="store_true", help="2 minutes")
    parser.add_argument("--window", type=float, default=30.0, help="seconds per window (default 30)")
    parser.add_argument("--sample", type=float, default=5.0, help="seconds between memory samples (default 5)")
    parser.add_argument("--warmup", type=float, default=60.0, help="seconds left out of the memory slope")
    parser.add_argument("--name", help="results/<name>.json and .png (default soak; soak-short with --quick, "
                                       "so a smoke run never replaces a long soak)")
    args = parser.parse_args()
    minutes = 2.0 if args.quick else args.minutes
    args.name = args.name or ("soak-short" if args.quick else "soak")
    print(f"soak: recording {minutes:g} min at full rate ...", file=sys.stderr)
    result, samples = soak(minutes, args.window, args.sample, args.warmup)
    result.update(quick=args.quick, name=args.name, memory_samples=samples)
    RESULTS.mkdir(exist_ok=True)
    plot(result, samples, RESULTS / f"{args.name}.png")
    write_result(args.name, result)


if __name__ == "__main__":
    main()
