"""BENCHMARKS.md section 5 (soak: recording at full rate for a long time) from results/soak.json (`make
soak`, 30 min) and results/soak-short.json (`make bench`, 5 min); used by report.py."""

from __future__ import annotations

import numpy as np

TARGET_P99_MS = 5.0
SHOWN_WINDOWS = 10  # rows of the per-window table (evenly spaced over the run, first and last included)
RUNS = (("soak", "`make soak`"), ("soak-short", "inside `make bench`"))

METHOD = (
    "`python -m midas_cli record --status-json` with the devices of section 1 (`midas emulate trakstar` "
    "4 × 220 Hz and `midas emulate fps` 9 channels at 850 Hz on pseudo-terminals, simulated video and "
    "HandKP at 30 Hz) for the whole run. The script reads the status line the recorder prints every "
    "second and every few seconds the resident memory (`VmRSS`, /proc) and CPU time of the recorder, of "
    "each of its child processes (one worker per device, multiprocessing's resource tracker) and of the "
    "emulators. The run is cut into windows: per window and stream, new samples, measured rate, new "
    "dropped / corrupt / sequence-missing records and latency (the status lines' `latency_window_ms`: "
    "host read -> handed to the OS, over the last ~10 s; lines 10 s apart, p99 = the largest of them). "
    "Loss at the end comes from the session manifest and the emulators' own counts; the memory slope is "
    "a least-squares line after the warm-up."
)


def soak_section(results: dict[str, dict | None]) -> list[str]:
    """Section 5 for whichever of results/soak.json and results/soak-short.json exist."""
    out = ["## 5. Soak: recording at full rate for a long time (`bench_soak.py`)", "", METHOD, ""]
    for name, how in RUNS:
        s = results.get(name)
        if s:
            out += soak_run(s, name, how)
        elif name == "soak":
            out += ["### 30 minutes: not run yet", "", "Run `make soak` (about 32 minutes) on a quiet machine; "
                    "`make bench` runs only the short soak below.", ""]
    return out


def soak_run(s: dict, name: str, how: str) -> list[str]:
    load = "–".join(f"{x:g}" for x in s["load_average_before_after"])
    out = [f"### {s['minutes']:g} minutes ({how}, `results/{name}.json`)", "",
           f"Run {s['machine']['date_utc']}, load {load} (1 min, before–after), {s['wall_s']:g} s wall, "
           f"{s['status_lines']} status lines, windows of {s['window_s']:g} s, memory every {s['sample_s']:g} s"
           + (" — **smoke run (`--quick`), not for comparison**." if s.get("quick") else "."), ""]
    out += stream_table(s) + [""] + memory_table(s) + [""] + window_table(s) + [""]
    out += [f"![soak memory and latency over time](benchmarks/results/{name}.png)", "", *reading(s), ""]
    return out


def stream_table(s: dict) -> list[str]:
    stab = s["latency_stability"]
    out = ["| stream | samples | rate Hz | lost (seq gaps + dropped + unexplained) | corrupt | sent by emulator − "
           "recorded | whole run p50 / p99 / max ms | window p99 first third -> last third ms | largest window "
           "p99 ms |", "|---|---|---|---|---|---|---|---|---|"]
    for stream, f in s["streams"].items():
        if not f.get("samples"):
            out.append(f"| {stream} | 0 | — | — | — | — | — | — | — |")
            continue
        lat, st = f["latency_ms"], stab.get(stream)
        trend = f"{st['p99_first_third_ms']:g} -> {st['p99_last_third_ms']:g}" if st else "—"
        largest = f"{st['p99_max_window_ms']:g}" if st else "—"
        out.append(f"| {stream} | {f['samples']} | {f['measured_rate_hz']:g} | {lost(f)} | {f['corrupt']} | "
                   f"{f.get('sent_minus_recorded', '—')} | {lat['p50']:g} / {lat['p99']:g} / {lat['max']:g} | "
                   f"{trend} | {largest} |")
    return out


def lost(f: dict) -> int:
    return f["seq_gaps_missing"] + f["queue_dropped"] + f["missing_unexplained"]


def memory_table(s: dict) -> list[str]:
    m = s["memory"]
    out = [f"Resident memory after the {m['warmup_s']:g} s warm-up ({m['samples']} samples):", "",
           "| process | MiB after warm-up | MiB at end | max MiB | slope MiB per 10 min |", "|---|---|---|---|---|"]
    rows = [("recorder + children (sum)", m["recorder_total"])]
    rows += [(f"{p['role']} (pid {pid})", p) for pid, p in m["processes"].items()]
    rows += [(f"emulator {n} (not part of midas record)", e) for n, e in m["emulators"].items()]
    for label, v in rows:
        out.append(f"| {label} | {_g(v['start_mib'])} | {_g(v['end_mib'])} | {_g(v['max_mib'])} | "
                   f"{_g(v['slope_mib_per_10min'])} |")
    return out


def window_table(s: dict) -> list[str]:
    wins = s["windows"]
    if not wins:
        return ["No complete window (the run was shorter than one window)."]
    names = list(wins[0]["streams"])
    picks = sorted({int(round(i)) for i in np.linspace(0, len(wins) - 1, min(SHOWN_WINDOWS, len(wins)))})
    out = [f"Per window ({len(picks)} of {len(wins)} shown, evenly spaced; all in the JSON): rate Hz / new "
           "losses / p99 ms per stream.", "",
           "| window s | load 1 min | recorder MiB (mean) | recorder CPU % of a core | emulators CPU % | "
           + " | ".join(names) + " |", "|---|---|---|---|---|" + "---|" * len(names)]
    for w in (wins[i] for i in picks):
        mem = w["memory"] or {}
        cells = []
        for n in names:
            st = w["streams"][n]
            new_lost = st["dropped"] + st["seq_missing"]
            p99 = st.get("latency_ms", {}).get("p99")
            cells.append(f"{_g(st['rate_hz'])} / {new_lost} / {_g(p99)}")
        out.append(f"| {w['start_s']:g}–{w['end_s']:g} | {_g(mem.get('load_1min'))} | "
                   f"{_g(mem.get('recorder_mean_mib'))} | {_g(mem.get('recorder_cpu_percent'))} | "
                   f"{_g(mem.get('emulators_cpu_percent'))} | " + " | ".join(cells) + " |")
    return out


def reading(s: dict) -> list[str]:
    """The run's verdicts in words: loss, memory growth, latency over time."""
    total_lost = sum(lost(f) for f in s["streams"].values() if f.get("samples"))
    empty = [n for n, f in s["streams"].items() if not f.get("samples")]
    mem = s["memory"]["recorder_total"]
    slope = mem["slope_mib_per_10min"]
    loss = ("**Reading.** Loss: none — no sequence gap, no queue drop and no unexplained missing record in "
            f"{s['minutes']:g} min" if total_lost == 0 and not empty else
            f"**Reading.** Loss: **{total_lost} records lost**" + (f", no samples at all from {', '.join(empty)}"
                                                                   if empty else ""))
    growth = ("Memory: not enough samples after the warm-up for a slope." if slope is None else
              f"Memory of the recorder and its workers: {_g(mem['start_mib'])} -> {_g(mem['end_mib'])} MiB after "
              f"the warm-up, slope {slope:+g} MiB per 10 min (a 3-hour session at this rate: "
              f"{slope * 18:+.0f} MiB); a run of a few minutes cannot separate a slow leak from allocator noise.")
    return [f"{loss}; the emulator's `sent − recorded` counts records still on the wire when the recorder "
            "stopped, not losses. " + growth + " " + latency_words(s), "", *emulator_words(s)]


def emulator_words(s: dict) -> list[str]:
    """The emulators share the machine with the recorder: their CPU, and the FPS emulator's growth."""
    cpu = [w["memory"]["emulators_cpu_percent"] for w in s["windows"]
           if w["memory"] and w["memory"].get("emulators_cpu_percent") is not None]
    out = []
    if cpu:
        out.append(f"* The emulators themselves used {np.mean(cpu):.0f} % of a core on average (of "
                   f"{s['machine']['cpus']} cores), beside the recorder's own CPU.")
    fps = s["memory"]["emulators"].get("fps", {})
    if (fps.get("slope_mib_per_10min") or 0) > 1:
        out.append(f"* `emulator fps` grows {fps['slope_mib_per_10min']:g} MiB per 10 min: run with `--summary`, it "
                   "keeps every sample it sent (`devices/fps/emulator.py` `keep_samples`) to write them at exit; "
                   "this is the test harness, not `midas record`.")
    return out


def latency_words(s: dict) -> str:
    if not s["latency_window_reported"]:
        return ("Latency over time: the recorder's status lines carried no `latency_window_ms`, so no "
                "per-window latency is shown (the whole-run figures come from the manifest).")
    parts = []
    for stream, st in s["latency_stability"].items():
        verdict = "" if stream == "video" else (" (over 5 ms)" if st["p99_last_third_ms"] > TARGET_P99_MS else "")
        parts.append(f"{stream} {st['p99_first_third_ms']:g} -> {st['p99_last_third_ms']:g} ms{verdict}")
    return ("Latency over time (median of the windows' p99, first third -> last third): " + ", ".join(parts) + ".")


def _g(value: float | None) -> str:
    return "—" if value is None else f"{value:g}"
