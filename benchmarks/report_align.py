"""BENCHMARKS.md section 2 (align vs merge_asof) from results/align.json; used by report.py."""

from __future__ import annotations

TARGET_SPEEDUP = 20.0

METHOD = (
    "A session (EmHT 4 × 240 Hz, FPS 9 ch × 250 Hz, HandKP 30 Hz, 30 fps video clock) is generated through "
    "`midas_cli/session/writer.py` and finalised like a recording, so it carries its binary stream copies "
    "(`streams/<name>.npy`, written when a session is finalised). Each side then runs in a fresh child "
    "process, the baseline three times and midas five (the median is shown), each run starting with no "
    "output on disk and the page cache's dirty pages flushed (`sync`): **work** = from the first file read "
    "to the aligned output on disk, after the side's imports; **process** = the whole child, interpreter start-up and imports "
    "included. Peak memory is the child's own `VmHWM`. Baseline (the original system's approach, CSV in, "
    "CSV out): `pd.read_csv` of each stream CSV, `pd.merge_asof(direction='backward', tolerance=3 sample "
    "periods)` onto the video frame times, `to_csv`. `midas align` memory-maps the copies, reads only the "
    "rows chosen for frames, computes the derived columns too (hand points, velocities, grasper distance, "
    "clutch, HandKP gap filling) and writes `derived/aligned.npz` (frames, times, column names), "
    "`aligned.values.npy` (the values, column-major) and `aligned.json`."
)

READING = [
    "**Reading.** Before the binary copies (commit 589bf20) `midas align` took 17 s on the 60-minute "
    "session, 0.38× the baseline: 25 of its 32 profiled seconds went to `aligned.csv` through pandas "
    "`to_csv(float_format='%.6g')` and 3.3 s to a compressed npz, and parsing the stream CSVs alone capped "
    "any CSV-in design near 3.5×. Three changes: (1) each stream CSV gets a binary copy when the session is "
    "finalised, which align memory-maps, touching only the rows it picks; (2) the aligned values are written "
    "as their own column-major `.npy` (no compression, no zip CRC, no redundant mask), which readers "
    "memory-map, the raw streams' columns on a second thread while the derived ones are computed (EmHT and "
    "HandKP features also run side by side); (3) `aligned.csv` is written only with `--csv`. The CSV "
    "stays the archival record; a copy is used only while it matches the CSV (sha256 in the manifest, "
    "size) and `session verify` compares them value by value.",
    "",
    "**Since then.** Checking that match hashes every stream CSV on each read (since issue 14: a copy "
    "made from another version of the CSV was used silently before); the streams are now read side by "
    "side so the hashing shares the two cores, but it is most of the work time on long sessions, which is "
    "why the work speed-up is ~12x where it was 22-28x without the check. The whole process got faster: "
    "`midas align` no longer imports `scipy.interpolate` (0.37 s; gap filling has its own not-a-knot "
    "spline on `scipy.linalg.solve_banded`, equal to CubicSpline), 0.73 -> 0.36 s at 10 minutes.",
    "",
    "**What it costs elsewhere.** The parse moved to the end of the recording: *copies at finalise* is "
    "the extra time `midas record` (or `simulate`, `import`, `repair`) spends when it stops, once per "
    "session. The copies take about as much disk as the CSVs. *From CSVs* is `midas align` on a session "
    "without copies (older sessions, or copies deleted): correct, but bound by parsing text. Process "
    "times include `midas`'s start-up (typer, rich, numpy, scipy.interpolate; a fixed ~1–2 s, paid once "
    "per `midas align sessions/*/` batch).",
]


def align_section(a: dict) -> list[str]:
    out = ["## 2. Align: `midas align` vs per-stream pandas `merge_asof` (`bench_align.py`)", "", METHOD, "",
           "| session | load 1 min | stream CSV MB | frames | baseline work s | midas work s | **speedup (work)** "
           "| baseline process s | midas process s | speedup (process) | baseline peak MiB | midas peak MiB "
           "| output equal |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for run in a["runs"]:
        b, m, c = run["baseline_merge_asof"], run["midas_align"], run["check"]
        out.append(f"| {run['minutes']:g} min | {run['load_average_before']:g} | {run['stream_csv_mb']:g} | "
                   f"{c['frames']} | {b['work_s']:g} | {m['work_s']:g} | **{run['speedup_work']:g}×** | "
                   f"{b['process_s']:g} | {m['process_s']:g} | {run['speedup_process']:g}× | "
                   f"{b['peak_rss_mib']:g} | {m['peak_rss_mib']:g} | "
                   f"{'yes' if c['equal'] else 'NO'} ({c['columns_compared']} columns) |")
    out += ["", "| session | midas work, all repeats s | baseline work, all repeats s | midas from CSVs (no copies) "
            "work s | speedup from CSVs | midas with `--csv` work s | copies at finalise s | copies MB | "
            "aligned output MB |", "|---|---|---|---|---|---|---|---|---|"]
    for run in a["runs"]:
        f, w = run["midas_align_from_csv"], run["midas_align_csv_too"]
        out.append(f"| {run['minutes']:g} min | {', '.join(f'{x:g}' for x in run['midas_align']['work_s_all'])} | "
                   f"{', '.join(f'{x:g}' for x in run['baseline_merge_asof']['work_s_all'])} | {f['work_s']:g} | "
                   f"{run['speedup_from_csv']:g}× | {w['work_s']:g} | {run['binary_copies_at_finalise_s']:g} | "
                   f"{run['stream_copies_mb']:g} | {run['aligned_output_mb']:g} |")
    check = a["runs"][0]["check"]
    out += ["", f"* Equality rule: {check['rule']}.",
            f"* Output width: midas {check['midas_columns']} columns (raw, per-stream delta, derived), "
            f"baseline {check['baseline_columns']}."]
    slope = a.get("work_seconds_per_session_minute")
    if slope:
        out.append("* Cost growth (least-squares slope of work seconds per session minute): "
                   f"baseline {slope['baseline_merge_asof']:g}, midas align {slope['midas_align']:g}, "
                   f"midas from CSVs {slope['midas_align_from_csv']:g}, midas with `--csv` "
                   f"{slope['midas_align_csv_too']:g}.")
    met = all(run["speedup_work"] >= TARGET_SPEEDUP and run["check"]["equal"] for run in a["runs"])
    out.append(f"* The issue's bar is >= {TARGET_SPEEDUP:g}× faster than the baseline, session files on disk to "
               f"aligned output on disk, identical values: **{'met' if met else 'not met'}** on the work time "
               "at every size above. Whole-process times are in the table too.")
    big = next((run for run in a["runs"] if run.get("profile")), None)
    if big:
        prof = big["profile"]
        out += ["", f"### Where `midas align` spends its time ({big['minutes']:g} min session)", "",
                f"cProfile of `align_and_write` in-process: {prof['align_and_write_s_profiled']:g} s in all; "
                f"CLI start-up alone (`python -m midas_cli --help`): {prof['cli_startup_s']:g} s.", "",
                "| stage | cumulative s |", "|---|---|"]
        out += [f"| {stage} | {sec:g} |" for stage, sec in sorted(prof["stages_cumulative_s"].items(),
                                                               key=lambda kv: -kv[1])]
    return out + ["", *READING, ""]
