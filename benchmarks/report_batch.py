"""BENCHMARKS.md sections for batch throughput (bench_batch.py) and export (bench_export.py)."""

from __future__ import annotations


def batch_section(b: dict) -> list[str]:
    m, n = b["machine"], b["sessions"]
    lines = ["## 7. Batch throughput: one call for many sessions vs one call each (`bench_batch.py`)", "",
             f"{n} copies of one {b['session_seconds']}-s simulated session; `midas CMD S1 .. S{n}` once against "
             f"{n} `midas CMD Si` run one after another (a shell loop), outputs removed between runs. Load average "
             f"{b['load_average_1min_before_after'][0]}–{b['load_average_1min_before_after'][1]}, {m['date_utc']}.", "",
             "| command | one call s | sessions/s | loop s | sessions/s | one call faster by | fixed cost per process s |",
             "|---|---|---|---|---|---|---|"]
    for name, c in b["cases"].items():
        lines.append(f"| `midas {name}` | {c['one_call_s']} | {c['one_call_sessions_per_s']} | {c['loop_s']} | "
                     f"{c['loop_sessions_per_s']} | {c['speedup']}x | {c['fixed_cost_per_process_s']} |")
    return lines + ["", "The fixed cost is the interpreter, typer and the command's imports (numpy and the align code; "
                    "`verify` adds pandas): paid once per call, so scripts should pass many sessions to one call.", ""]


def export_section(e: dict) -> list[str]:
    m = e["machine"]
    lines = ["## 8. Export of long sessions (`bench_export.py`)", "",
             "bench_align's session (EmHT 4 x 240 Hz, FPS 9 ch x 250 Hz, HandKP 30 Hz, video clock 30 fps), one "
             "`midas export SESSION --format F` process per format: wall seconds of the whole process, its own "
             "peak resident memory (VmHWM) and the files written. Streams are read and written a piece at a "
             f"time, so memory should not grow with length. Load average {e['load_average_1min_before_after'][0]}–"
             f"{e['load_average_1min_before_after'][1]}, {m['date_utc']}.", "",
             "| session | stream CSV MB | format | wall s | peak RSS MiB | output MB |", "|---|---|---|---|---|---|"]
    for run in e["runs"]:
        for fmt, f in run["formats"].items():
            lines.append(f"| {run['minutes']:g} min | {run['stream_csv_mb']} | {fmt} | {f['wall_s']} | "
                         f"{f['peak_rss_mib']} | {f['output_mb']} |")
    if len(e["runs"]) >= 2:
        a, b = e["runs"][0], e["runs"][-1]
        growth = ", ".join(f"{fmt} {a['formats'][fmt]['peak_rss_mib']} -> {b['formats'][fmt]['peak_rss_mib']} MiB"
                           for fmt in a["formats"])
        lines += ["", f"Peak memory, {a['minutes']:g} -> {b['minutes']:g} min: {growth}."]
    lines += ["", "MCAP is written with foxglove-sdk since issue 24: besides the JSON rows, every EmHT row is a "
              "`foxglove.FrameTransforms` message (4 sensors, float64 metres and quaternions), which compresses far "
              "less than the JSON text. The JSON-only file it replaced took 47.5 s and 228 MB for the 60-minute "
              "session (2026-11-25, load 2–4): about 2–3x the time and 2x the size now, for the 3-D panel.",
              "",
              "LeRobot reads the aligned table (`midas align` runs first, untimed) and writes one episode; this "
              "session has no console recording, so no video is encoded (a session with one also copies its "
              "frames to MP4: not timed here). Parquet also writes `aligned.parquet` for an aligned session."]
    return lines + [""]


def foxglove_live_section(r: dict) -> list[str]:
    """Recording CPU with `record --foxglove` and a subscribed client, against off (bench_foxglove_live.py)."""
    m = r["machine"]
    lines = ["## 9. Live view in Foxglove: recording CPU (`bench_foxglove_live.py`)", "",
             "`midas record --simulate` (EmHT 4 x 240 Hz, FPS 9 ch x 250 Hz, video and HandKP 30 Hz, simulated), "
             "alternately without and with `--foxglove` and a websocket-client subscribed to every channel; CPU "
             "of the recorder process over the middle of the recording (40 % to 90 % of --duration), % of one "
             f"core. The server lives in the recorder: the workers run no new code. {m['date_utc']}.", "",
             "| run | --foxglove | load 1 min | window s | recorder % of one core | workers % (sum) | messages received |",
             "|---|---|---|---|---|---|---|"]
    for k, run in enumerate(r["runs"]):
        cpu = run["steady_cpu_percent_of_one_core"]
        received = sum(run["messages_received"].values())
        load = run["load_average_before_after"]
        workers = round(sum(v for k, v in cpu["percent"].items() if k.startswith("worker ")), 1)
        lines.append(f"| {k // 2 + 1} | {'on' if run['foxglove'] else 'off'} | {load[0]}–{load[1]} | "
                     f"{cpu['window_s']} | {cpu['percent'].get('recorder', '—')} | {workers} | "
                     f"{received if run['foxglove'] else '—'} |")
    recorder = {on: [r["steady_cpu_percent_of_one_core"]["percent"].get("recorder", 0.0) for r in r["runs"]
                     if r["foxglove"] == on] for on in (False, True)}
    if all(recorder.values()):
        extra = sum(recorder[True]) / len(recorder[True]) - sum(recorder[False]) / len(recorder[False])
        lines += ["", f"With a client subscribed the recorder spends {extra:.1f} % more of one core (one JSON row per "
                  "batch and the EmHT transforms encoded); the workers run no new code, their figures move with the "
                  "machine's load. With no client subscribed nothing is encoded."]
    return lines + [""]
