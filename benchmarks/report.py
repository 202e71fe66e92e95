"""Render BENCHMARKS.md at the repository root from benchmarks/results/*.json (run by `make bench`)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import RESULTS, machine_info  # noqa: E402
from report_align import align_section  # noqa: E402
from report_reference import reference_section  # noqa: E402
from report_batch import batch_section, export_section, foxglove_live_section  # noqa: E402
from report_executor import executor_section  # noqa: E402
from report_fold_batch import fold_batch_section  # noqa: E402
from report_gestures import gestures_jigsaws_section, rescored_section  # noqa: E402
from report_live import live_section  # noqa: E402
from report_soak import soak_section  # noqa: E402
from report_timestamp import timestamp_section  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
TARGET_P99_MS = 5.0


def load(name: str) -> dict | None:
    path = RESULTS / f"{name}.json"
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None


def header() -> list[str]:
    m = machine_info()
    return ["# Benchmarks", "",
            "Written by `make bench` (benchmarks/report.py) from `benchmarks/results/*.json`; do not edit by hand.",
            "Nothing here is a test: no figure is asserted. Every figure is recorded with the 1-minute load",
            "average, because the machine may be shared; compare runs only at similar load.", "",
            f"* Machine: {m['cpus']} CPUs (`nproc`), {m['cpu_model']}, {m['memory_gib']} GiB memory, "
            f"{m['platform']}, Python {m['python']}",
            f"* Rendered: {m['date_utc']}", "",
            "Commands (each also runs alone; `--quick` is a short smoke mode):", "", "```sh",
            "make bench                                      # all of the below, then this file",
            "make soak                                       # the 30-minute soak alone (SOAK_MIN=30), then this file",
            ".venv/bin/python benchmarks/bench_record.py     # recording latency/loss/CPU, 10 s and 30 s",
            ".venv/bin/python benchmarks/bench_soak.py --minutes 5 --name soak-short   # the soak inside make bench",
            ".venv/bin/python benchmarks/bench_soak.py       # make soak: 30 min -> results/soak.json",
            ".venv/bin/python benchmarks/bench_align.py      # align vs merge_asof, 10, 30 and 60 min sessions",
            ".venv/bin/python benchmarks/bench_pedal_gt.py --duration 10   # pedal ground truth from video",
            ".venv/bin/python benchmarks/bench_train.py      # simulate + align 15 trials; MS-TCN++ / transformer",
            ".venv/bin/python benchmarks/bench_train.py --louo   # one JIGSAWS-sized LOUO fold of MS-TCN++",
            "nice -n 19 .venv/bin/python benchmarks/bench_train.py --louo-all   # a whole Suturing-sized LOUO at the defaults",
            ".venv/bin/python benchmarks/bench_mstcn_reference.py --threads 1   # MS-TCN++ vs a reference loop",
            ".venv/bin/python benchmarks/bench_fold_batch.py   # batched folds without a GPU: operators a step",
            "nice -n 19 .venv/bin/python benchmarks/gestures_jigsaws.py --jobs 2   # LOUO on real JIGSAWS kinematics",
            ".venv/bin/python benchmarks/bench_startup.py    # start-up of light commands vs a bare python",
            ".venv/bin/python benchmarks/bench_batch.py      # align / verify over 400 sessions: one call vs 400",
            ".venv/bin/python benchmarks/bench_export.py     # export to MCAP / Parquet / XDF, 10 and 60 min",
            ".venv/bin/python benchmarks/bench_executor.py   # align through --jobs 1, 2 and a one-node SLURM",
            ".venv/bin/python benchmarks/bench_foxglove_live.py   # recording CPU with record --foxglove on/off",
            ".venv/bin/python benchmarks/bench_timestamp_error.py   # t_host_ns against the emulators' send times",
            ".venv/bin/python benchmarks/report.py           # this file", "```", ""]


def _ms(d: dict | None, key: str) -> str:
    return "—" if not d or d.get(key) is None else f"{d[key]:g}"


def record_section(r: dict) -> list[str]:
    out = ["## 1. Recording latency and loss (`bench_record.py`)", "",
           "`python -m midas_cli record` with every device at full rate through the real serial code path:",
           "`" + "`, `".join(r["devices"]) + "` (EmHT and FPS are `midas emulate trakstar` / `midas emulate fps` on",
           "pseudo-terminals; EmHT at 220 Hz, the most 4 sensors' 13-byte POSITION/ANGLES records carry at the",
           "trakSTAR's 115200 baud (the issue's 4 × 240 Hz needs 124.8 kbit/s: only the USB `atc3dg://` backend",
           "reaches it); FPS at 850 Hz, the most 9 channels carry at 500000 baud). Latency is the",
           "manifest's `latency_ms`: host read (`t_host_ns`) -> written to the OS (write + flush), 50 µs bins.",
           f"Target: p99 <= {TARGET_P99_MS:g} ms per non-video stream. Paper means (Appendix A.1): "
           + ", ".join(f"{k} {v} ms" for k, v in r["paper_mean_ms"].items()) + ".", ""]
    out += ["| run | load 1 min | stream | samples | rate Hz | p50 ms | p95 ms | p99 ms | max ms | p99 <= 5 ms "
            "| lost (seq gaps + dropped) | sent by emulator − recorded | bytes/min |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for run in r["runs"]:
        load = "–".join(f"{x:g}" for x in run["load_average_before_after"])
        for name, s in run["streams"].items():
            lat = s["latency_ms"]
            lost = s["seq_gaps_missing"] + s["queue_dropped"] + s["missing_unexplained"]
            ok = "video clock" if name == "video" else ("yes" if lat["p99"] <= TARGET_P99_MS else "**no**")
            out.append(f"| {run['duration_s']:g} s | {load} | {name} | {s['samples']} | {s['measured_rate_hz']:g} | "
                       f"{lat['p50']:g} | {lat['p95']:g} | {lat['p99']:g} | {lat['max']:g} | {ok} | {lost} | "
                       f"{s.get('sent_minus_recorded', '—')} | {s['bytes_per_minute']:,} |")
    out += [""] + [f"* {run['duration_s']:g} s run: recorder CPU {run['recorder_cpu_s']:g} s over {run['wall_s']:g} s "
                   f"wall = {run['recorder_cpu_percent_of_one_core']:g} % of one core ({run['cpu_note']})."
                   for run in r["runs"]]
    out += [f"* {run['duration_s']:g} s run, steady state ({run['steady_cpu_percent_of_one_core']['window_s']:g} s "
            "from 40 % to 90 % of the recording, per process from /proc, % of one core): "
            + ", ".join(f"{k} {v:g}" for k, v in run["steady_cpu_percent_of_one_core"]["percent"].items()
                        if k != "other") + f" (issue 17 goal: total <= {CPU_GOAL_PERCENT:g} %)."
            for run in r["runs"] if "steady_cpu_percent_of_one_core" in run]
    out += ["* `sent − recorded` counts records the emulator put on the wire after the recorder stopped reading "
            "(1–2 at stop), not losses: sequence numbers inside the recording have no gaps.", ""]
    return out + record_profile(r)


def record_profile(r: dict) -> list[str]:
    p = r["stage_profile"]
    window, transit = p["worker_batch_window"], p["queue_transit_ms"]["idle_parent"]
    out = ["### Where the recording latency goes", "",
           "Each device worker process reads, formats and appends its rows to the stream file itself, then sends "
           "the recorder only bookkeeping (sequence numbers, times, bytes); the recorder fsyncs the files once a "
           "second through its own descriptors. Three measurements split the path (load " +
           "–".join(f"{x:g}" for x in p["load_average_before_after"]) + "):", "",
           "1. **Worker loop** — each device alone, in one process, through the worker's own loop "
           "(`record/worker.py` `_pump`) writing to scratch files: what the device's `read()` adds (for the FOB "
           "decoder: the idle window that confirms a record's end) before the write.",
           "2. **In the recorder** — every device at once, with a display-like `snapshot()` every 0.25 s: read -> "
           "the worker's write starts, the write itself, read -> committed (the latency the manifest reports), "
           "and committed -> the recorder's bookkeeping thread (not part of the latency any more).",
           f"3. **mp.Queue transit** — a spawned process puts `DataBatch`es ({transit['rows_per_batch']} rows) at "
           f"{transit['rate_hz']:g} Hz; parent `get()` time − put time: the hop the data no longer takes.", "",
           "| stream | 1. worker loop p50 / p99 ms | 2. read -> write starts p50 / p99 ms | 2. write p50 / p99 ms "
           "| 2. read -> committed p50 / p99 ms | 2. committed -> recorder p50 / p99 ms | rows per batch |",
           "|---|---|---|---|---|---|---|"]
    for name, s in p["streams"].items():
        w = window.get(name) or {}
        rc, cr = s.get("read_to_committed_ms") or {}, s.get("committed_to_recorder_ms") or {}
        out.append(f"| {name} | {_ms(w, 'p50')} / {_ms(w, 'p99')} | {s['read_to_writer_thread_ms']['p50']:g} / "
                   f"{s['read_to_writer_thread_ms']['p99']:g} | {s['write_ms']['p50']:g} / {s['write_ms']['p99']:g} | "
                   f"{_ms(rc, 'p50')} / {_ms(rc, 'p99')} | {_ms(cr, 'p50')} / {_ms(cr, 'p99')} | "
                   f"{s['rows_per_batch_mean']:g} |")
    out += ["", f"mp.Queue transit alone: p50 {transit['p50']:g} ms, p95 {transit['p95']:g} ms, p99 {transit['p99']:g} ms, "
            f"max {transit['max']:g} ms (n = {transit['n']}).", "", *RECORD_ANALYSIS, *record_growth(r), ""]
    return out


CPU_GOAL_PERCENT = 15.0

RECORD_ANALYSIS = [
    "**Reading.** The write is a few tens of microseconds; what is left of the latency is the device's own "
    "read path. History of this figure:",
    "",
    "* Commit 5ec329c: workers flushed only after a 5 ms batch window, checked after each blocking `read()`: "
    "p99 7–15 ms. Commit 0d035f8: rows handed over as soon as a read returns: p99 ~5 ms for FPS, video and "
    "HandKP, but the hop through the pickled `mp.Queue` to the recorder's writer thread (which shares its "
    "GIL with the display) had a tail of several ms whenever two cores carry emulators, four workers and "
    "the recorder.",
    "* Now the worker writes its rows itself (commit b3a1053): no second process has to be scheduled "
    "between a read and the disk, and a full queue can only delay bookkeeping, never drop rows. The "
    "recorder-side hop (column 2, committed -> recorder) still has that tail, but nothing waits on it.",
    "* CPU (issue 17): one bookkeeping message per read (850 a second from the pedal board) cost a thread "
    "hand-off, a pickle and a pipe write in the worker and the same in the recorder; workers now gather "
    "it and send it at most every 50 ms (rows are on disk at once as before; column 2's committed -> "
    "recorder hop is therefore up to 50 ms, and rows per batch grew), the live screen's latency percentiles "
    "read only the histogram bins in use, and the pedal states are computed without numpy per sample. "
    "Steady-state CPU of recorder + workers at this load went from 36.8 % to about 17 % of one core "
    "(2026-11-25, a probe of /proc per process, load 1.6–5.8). The goal (<= 15 %) is **not met**: what is "
    "left is per-sample Python in the readers (the pedal worker decodes, formats and writes 850 rows a "
    "second, one read each; EmHT waits on an idle window per record) and the simulated video/HandKP "
    "generators. Reading the pedal board at most every 2 ms would save a third of its worker (tried: "
    "9 -> 6 %) but stamps the 2-3 samples of one read with one host time, so it was not kept; a C/Cython "
    "reader or a board that sends blocks would be the next step. (`recorder CPU` from RUSAGE_CHILDREN "
    "above counts only what the recorder reaps itself: since the fork-server workers it is not the "
    "whole cost, and the steady-state line is the figure to compare.)",
    "* EmHT: the Flock-of-Birds stream has no checksum, so the decoder confirmed a record's end only when "
    "the next record's first byte arrived: the last record of each 4-sensor group waited a whole cycle "
    "(p50 5.3 ms at 200 Hz). It is now accepted once the line has stayed idle for a short window after "
    "it (an inserted byte would follow at wire speed), which bounds that wait (column 1).",
    "",
]


def record_growth(r: dict) -> list[str]:
    """How cost grows with recording length, from the runs (first vs last)."""
    if len(r["runs"]) < 2:
        return ["Cost growth: only one duration in this run (use the full mode for two)."]
    a, b = r["runs"][0], r["runs"][-1]
    p99 = ", ".join(f"{n} {a['streams'][n]['latency_ms']['p99']:g} -> {b['streams'][n]['latency_ms']['p99']:g} ms"
                    for n in a["streams"])
    return [f"Cost growth, {a['duration_s']:g} s -> {b['duration_s']:g} s: recorder CPU "
            f"{a['recorder_cpu_s']:g} -> {b['recorder_cpu_s']:g} s "
            f"({a['recorder_cpu_percent_of_one_core']:g} -> {b['recorder_cpu_percent_of_one_core']:g} % of a core, "
            f"the shorter run carrying more start-up share); slope "
            f"{(b['recorder_cpu_s'] - a['recorder_cpu_s']) / (b['duration_s'] - a['duration_s']):.3f} CPU s per "
            f"recorded s. p99 latency: {p99}."]


def pedal_section(p: dict) -> list[str]:
    load = p["machine"].get("load_average_1min_before_after", [])
    out = ["## 3. Pedal ground truth from video (`bench_pedal_gt.py`)", "",
           f"Seeded synthetic da Vinci Xi console video, davinci-xi layout, {p['cases'][0]['frames']} frames per case "
           f"unless named (date {p['date_utc']}, load {'–'.join(f'{x:g}' for x in load)}). Real time is "
           f"{p['real_time_fps']:g} fps.", "",
           "| video | frame | frames | decode only fps | extraction fps | × real time | min F1 | max onset error (frames) |",
           "|---|---|---|---|---|---|---|---|"]
    for c in p["cases"]:
        out.append(f"| {c['video']} | {c['frame_size'][0]}×{c['frame_size'][1]} | {c['frames']} | "
                   f"{c['decode_only_fps']:g} | {c['extract_fps']:g} | {c['x_real_time']:g} | {c['min_f1']:g} | "
                   f"{c['max_onset_error_frames']} |")
    return out + [""] + pedal_growth(p) + ["", "See benchmarks/README.md for the reading of these figures.", ""]


def pedal_growth(p: dict) -> list[str]:
    """How the cost grows with pixels (fitted slope) and with the number of frames (two 1080p lengths)."""
    out = []
    slope = p.get("pixel_slope")
    if slope:
        ex, de = slope["extract"], slope["decode_only"]
        out.append(f"* Cost per frame against the decoded frame's size ({', '.join(slope['cases'])}: "
                   f"{', '.join(f'{x:g}' for x in slope['megapixels'])} MP; least squares): extraction "
                   f"{ex['us_per_megapixel_per_frame']:g} µs per megapixel per frame {ex['intercept_us_per_frame']:+g} µs; "
                   f"decoding alone {de['us_per_megapixel_per_frame']:g} µs per megapixel "
                   f"{de['intercept_us_per_frame']:+g} µs (the stereo video is decoded whole, its left view "
                   f"measured). A 1080p frame (2.07 MP) is ~"
                   f"{(ex['us_per_megapixel_per_frame'] * 2.0736 + ex['intercept_us_per_frame']) / 1e3:.1f} ms of the "
                   f"33.3 ms a real-time frame allows.")
    by_size = [c for c in p["cases"] if c["frame_size"] == [1920, 1080] and c["video"].startswith("mono")]
    if len(by_size) >= 2:
        ordered = sorted(by_size, key=lambda c: c["frames"])
        a, b = ordered[0], ordered[-1]
        ms_a, ms_b = 1e3 / a["extract_fps"], 1e3 / b["extract_fps"]
        verdict = ("the same within 15 %: time grows linearly with the video's length" if abs(ms_b / ms_a - 1) <= 0.15
                   else f"{100 * (ms_b / ms_a - 1):+.0f} % per frame for the longer video; short videos are "
                        "dominated by start-up and load noise, compare at similar load")
        out.append(f"* Frames: 1080p at {a['frames']} and {b['frames']} frames, {ms_a:.2f} and {ms_b:.2f} ms per "
                   f"extracted frame: {verdict}.")
    jobs = p.get("two_videos_mono_1080p")
    if jobs:
        out.append(f"* Two 1080p videos at once: {jobs['jobs_1_fps']:g} fps aggregate with `--jobs 1`, "
                   f"{jobs['jobs_2_fps']:g} fps with `--jobs 2`.")
    return out


def train_section(t: dict) -> list[str]:
    if "data" not in t:
        return ["## 4. Gesture models on CPU (`bench_train.py`)", "",
                "results/train.json comes from an older bench_train.py (random features): run "
                "`.venv/bin/python benchmarks/bench_train.py` again.", ""]
    d, r0 = t["data"], t["runs"][0]
    cut = f"cut to {d['max_seconds_per_trial']:g} s each" if d["max_seconds_per_trial"] else "full length"
    prep_load = "–".join(f"{x:g}" for x in d["load_average_before_after"])
    out = ["## 4. Gesture models on CPU (`bench_train.py`)", "",
           f"Data: `midas simulate dataset --platform {d['platform']} --trials {d['trials']} --seed {d['seed']}` "
           f"(trials {cut}; {d['video_frames_total']} video frames, {d['dataset_mb']:g} MB) took "
           f"{d['simulate_s']:g} s, `midas align` of every session {d['align_s']:g} s (both `--jobs {d['jobs']}`, "
           f"load {prep_load}). Each case then reads the first N aligned sessions through "
           f"`models.data.build_dataset` ({' + '.join(t['dataset_config']['modalities'])}; "
           f"{', '.join(t['dataset_config']['features'])}; {', '.join(f'{k} {v}' for k, v in r0['modality_dims'].items())} "
           f"features; up to {max(r['classes'] for r in t['runs'])} gesture classes; {r0['rate_hz']:g} Hz as in "
           "the paper), normalises, and trains whole trials with the real loop (`models.train.fit`, Adam, batch "
           f"4): {t['timed_epochs']} epoch{'s' if t['timed_epochs'] > 1 else ''} timed after a warm-up, each case "
           "in its own process (peak = its VmHWM, dataset included). "
           "Online: one forward pass per new frame over a trailing context, batch 1, one torch thread; the "
           "paper's budget is a 400–900 ms human reaction window.", "",
           "| model | trials | frames (mean per trial) | load 1 min | build dataset s | epoch s | torch threads | "
           "peak MiB | online context | online p50 ms | online p99 ms |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in t["runs"]:
        o = r["online"]
        load = "–".join(f"{x:g}" for x in r["load_average_before_after"])
        out.append(f"| {r['model']} | {r['trials']} | {r['frames_total']} ({r['frames_per_trial_mean']:g}) | {load} | "
                   f"{r['dataset_build_s']:g} | {r['epoch_s']:g} | {r['torch_threads']} | {r['peak_rss_mib']:g} | "
                   f"{o['context_frames']} | {o['p50_ms']:g} | {o['p99_ms']:g} |")
    out.append("")
    for model, sl in t["slopes"].items():
        out.append(f"* {model}: {sl['epoch_s_per_1000_frames']:.3f} s per epoch and "
                   f"{sl['peak_mib_per_1000_frames']:.1f} MiB peak per 1000 training frames (least squares over the sizes).")
    return out + ["* Training uses torch's default thread count (one per core). On a machine already loaded beyond "
                  "its cores, OpenMP's waiting threads made the same epochs an order of magnitude slower in a "
                  "trial run; compare at similar load, and keep online inference at one thread.", ""]


def train_louo_section(t: dict) -> list[str]:
    d, m, r0 = t["data"], t["machine"], t["runs"][0]
    cut = f" --max-seconds {d['max_seconds_per_trial']:g}" if d["max_seconds_per_trial"] else ""
    out = ["### One LOUO fold, JIGSAWS-sized (`bench_train.py --louo`)", "",
           f"Data: `midas simulate dataset --platform {d['platform']} --trials {d['trials']} --subjects {d['subjects']} "
           f"--seed {d['seed']}{cut}` (default `--difficulty real`; {d['video_frames_total']} video frames, "
           f"{d['dataset_mb']:g} MB) took {d['simulate_s']:g} s, `midas align` {d['align_s']:g} s (`--jobs {d['jobs']}`). "
           f"The fold: MS-TCN++ on {' + '.join(t['dataset_config']['modalities'])} "
           f"({', '.join(t['dataset_config']['features'])}) at {r0['rate_hz']:g} Hz, {r0['columns']} columns, LOUO "
           f"fold 0 ({r0['trials']['train']} trials train, {r0['trials']['val']} validation, {r0['trials']['test']} "
           f"test), the MS-TCN++ recipe (batch {r0.get('batch_size', '?')}) through the real loop "
           "(`models.train.fit`); a warm-up epoch, then the timed epochs; **the "
           f"{r0['fold_epochs']}-epoch fold time is extrapolated** ({r0['fold_epochs']} x epoch + test prediction), "
           f"not measured. Machine: {m['cpu_model']}, {m['affinity_cpus']} usable CPUs of {m['cpus']}, "
           f"{m['date_utc']}.", "",
           "| device | columns | trials train/val/test | frames train/val/test | frames per trial | load 1 min | "
           f"epoch s (timed epochs) | test predict s | {r0['fold_epochs']}-epoch fold s (extrapolated) |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in t["runs"]:
        load = "–".join(f"{x:g}" for x in r["load_average_before_after"])
        trials = "/".join(str(r["trials"][p]) for p in ("train", "val", "test"))
        frames = "/".join(str(r["frames"][p]) for p in ("train", "val", "test"))
        out.append(f"| {r['device']} ({r['torch_threads']} torch threads) | {r['columns']} | {trials} | {frames} | "
                   f"{r['frames_per_trial_mean']:g} | {load} | {r['epoch_s']:g} ({r['timed_epochs']}) | "
                   f"{r['test_predict_s']:g} | {r['fold_s_extrapolated']:g} |")
    if not t.get("gpu_available"):
        out.append("| GPU | — | — | — | — | — | not measured: no GPU on this machine | — | — |")
    return out + [""]


def train_louo_all_section(results: list[dict]) -> list[str]:
    """Whole Suturing-sized cross-validations (``bench_train.py --louo-all``), one row per run."""
    d = results[0]["data"]
    out = ["### A whole LOUO cross-validation, Suturing-sized (`bench_train.py --louo-all`)", "",
           f"Data: `midas simulate dataset --platform {d['platform']} --trials {d['trials']} --subjects {d['subjects']} "
           f"--max-seconds {d['max_seconds_per_trial']:g}` (JIGSAWS Suturing: 38 labelled trials, 8 users, ~3,000 frames "
           "at 30 Hz each), aligned; then `midas train gestures SESSIONS --modalities mtm,psm --split louo --fold all "
           "--no-baseline --jobs 2` at the defaults of the commit that ran (its default model, features and model rate) "
           "through the CLI, measured "
           "end to end (on a GPU: `--accelerator cuda` instead of `--jobs 2`, the folds batched in one process). "
           "Issue 27's budget: <= 30 min on 2 CPU cores, <= 2 min on one H100. The machine is shared: the load is beside each run.",
           "", "| model | epochs | trials | frames at the model rate | inputs a frame | wall | a fold | load 1 min "
           "| in budget | run on | code |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        run, secs = r["run"], list(r["run"]["fold_seconds"].values())
        load = "–".join(f"{x:g}" for x in run["load_average_before_after"])
        span = f"{min(secs) / 60:.1f}–{max(secs) / 60:.1f} min" if secs else "—"
        quick = " (smoke run)" if r.get("quick") else ""
        gpu = r["machine"].get("gpu")
        budget = 120 if gpu else 1800
        where = gpu or f"{r['machine']['affinity_cpus']} CPUs"
        out.append(f"| {run.get('model', 'mstcn')} | {run['epochs']} | {run['trials']} | "
                   f"{run['frames_at_model_rate']:,} ({run['rate_hz']:g} Hz) | {sum(run['inputs'].values())} | "
                   f"{run['wall_s'] / 60:.1f} min{quick} | {span} | {load} | {'yes' if run['wall_s'] <= budget else 'no'} | "
                   f"{r['machine']['date_utc'][:16]}, {where} | "
                   f"{(run.get('git_commit') or '—')[:7]} |")
    return out + ["", "*epochs*: the defaults of the commit that ran (*code*) unless `--epochs` was given; MS-TCN++'s "
                  "default fell from 100 to 50 in 6169ad0 and to 20 (with shifted inputs) in 2fba614; since 79f463f the "
                  "default model is the ensemble (two MS-TCN++ at 20 epochs and two transformers at 10, trained one "
                  "after another: 20+10+20+10; since 945d0a5 one transformer: 20+10+20; README, \"Defaults and why\"); "
                  "*code* also sets the speed of a step "
                  "(193b339: ~0.7x the time of the published layout, the reference comparison below; 3c4339e: a step "
                  "~0.95x that of before, `models/mstcn.py`).", ""]


def members_section(r: dict) -> list[str]:
    """bench_members.py: what each member of the default ensemble costs to train (CPU time, not wall)."""
    epoch, member = r["epoch_median_cpu_s"], r["member_cpu_s"]
    return ["### The ensemble's members: training cost (`bench_members.py`)", "",
            f"One epoch of each network through the real loop on {r['task'].replace('_', ' ').title()} LOUO fold "
            f"{r['fold']} ({r['train_frames']:,} training frames at 10 Hz, each model's recipe), the two alternating "
            f"{len(r['epoch_cpu_s']['mstcn'])} times, CPU seconds of the process (one torch thread), median; "
            f"{r['machine']['cpu_model']}, {r['machine']['date_utc'][:16]}, torch {r['torch']}. CPU time, not wall: "
            "a wall time on the shared host moves with its load by more than a member's share.", "",
            "| network | epoch CPU s (each) | median | epochs (recipe) | a member, CPU s |", "|---|---|---|---|---|",
            *[f"| {name} | {', '.join(f'{v:.2f}' for v in r['epoch_cpu_s'][name])} | {epoch[name]:.2f} | "
              f"{round(member[name] / epoch[name])} | {member[name]:.0f} |" for name in epoch], "",
            f"* **The default ensemble ({' + '.join(r['members'])}): {r['ensemble_cpu_s']:.0f} CPU s a fold, "
            f"{r['ratio_to_four']:.2f}x the four-member ensemble of before ({r['four_members_cpu_s']:.0f} s).**", ""]


def startup_section(s: dict) -> list[str]:
    m = s["machine"]
    lines = ["## 6. Start-up of light commands (`bench_startup.py`)", "",
             "Whole `python -m midas_cli ...` processes against a bare `python -c pass`, run in turn; the ratio is",
             f"taken pair by pair, median of {s['runs']} (min–max beside it). The session commands read a small",
             "session from `midas simulate dataset --trials 1 --max-seconds 5`. Goals (issue 17): --version and",
             f"--help <= 3x, session info|list|verify <= 6x. Load average {s['load_average_1min_before_after'][0]}–"
             f"{s['load_average_1min_before_after'][1]}, {m['date_utc']}.", "",
             "| command | median s | bare python s | ratio (median) | min–max | goal | met |",
             "|---|---|---|---|---|---|---|"]
    for c in s["cases"].values():
        lines.append(f"| `{c['command']}` | {c['median_s']:.3f} | {c['bare_median_s']:.3f} | {c['ratio_median']:.1f}x | "
                     f"{c['ratio_min']:.1f}–{c['ratio_max']:.1f} | <= {c['goal']:g}x | {'yes' if c['meets_goal'] else 'no'} |")
    return lines + ["", "Before the start-up work (2026-11-25, same machine, load ~1.5, median of 10): --version 70x "
                    "(1.68 s), --help 69x, session info 13.6x, session list 14.1x, session verify 29.6x.", "",
                    "`--version` and the root `--help` are answered before typer is imported (commands/root.py).",
                    "Any command typer runs pays typer (~30 ms) and the pydantic it builds parameter coercion with",
                    "(~60-90 ms) on this machine; `session verify` also loads numpy and pandas (the strict value",
                    "parser).", ""]


def notes(section: str) -> list[str]:
    """Measurements and readings written by hand, without a script of their own, kept after ``section``'s
    generated part (``benchmarks/notes/<section>.md``, as it is): a render never loses them."""
    path = Path(__file__).resolve().parent / "notes" / f"{section}.md"
    return path.read_text(encoding="utf-8").rstrip("\n").splitlines() + [""] if path.is_file() else []


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    lines = header()
    quick = [name for name in ("startup", "record", "align", "train", "executor", "soak", "soak-short",
                               "mstcn_reference", "batch", "export", "fold_batch") if (load(name) or {}).get("quick")]
    if quick:
        lines += [f"**Smoke run** (`--quick`) for {', '.join(quick)}: short sizes, not for comparison.", ""]
    for name, section in (("record", record_section), ("align", align_section), ("pedal_gt", pedal_section),
                          ("train", train_section), ("executor", executor_section)):
        result = load(name)
        lines += section(result) if result else [f"## {name}: no results yet (run its script)", ""]
        if name == "train" and load("train_louo"):
            lines += train_louo_section(load("train_louo"))
        louo_all = sorted((json.loads(p.read_text(encoding="utf-8")) for p in RESULTS.glob("train_louo_all*.json")),
                          key=lambda r: r["machine"]["date_utc"])  # oldest first
        if name == "train" and louo_all:
            lines += train_louo_all_section(louo_all)
        if name == "train" and load("ensemble_members"):
            lines += members_section(load("ensemble_members"))
        if name == "train" and load("fold_batch"):
            lines += fold_batch_section(load("fold_batch"))
        if name == "train" and load("mstcn_reference"):
            lines += reference_section(load("mstcn_reference"))
        if name == "train" and load("gestures_jigsaws"):
            lines += gestures_jigsaws_section(load("gestures_jigsaws"))
            rescored = load("gestures_jigsaws_rescored")
            lines += rescored_section(rescored) if rescored else []
        lines += notes(name)
    lines += soak_section({name: load(name) for name in ("soak", "soak-short")})
    startup = load("startup")
    lines += startup_section(startup) if startup else ["## startup: no results yet (run its script)", ""]
    batch = load("batch")
    lines += batch_section(batch) if batch else ["## batch: no results yet (run its script)", ""]
    export = load("export")
    lines += export_section(export) if export else ["## export: no results yet (run its script)", ""]
    live = load("foxglove_live")
    lines += foxglove_live_section(live) if live else ["## foxglove_live: no results yet (run its script)", ""]
    stamps = load("timestamp_error")
    lines += timestamp_section(stamps) if stamps else ["## timestamp_error: no results yet (run its script)", ""]
    lines += notes("timestamp_error")
    lines += live_section(load("live_gestures"), load("live_record"))
    (ROOT / "BENCHMARKS.md").write_text("\n".join(lines), encoding="utf-8")
    print(ROOT / "BENCHMARKS.md")


if __name__ == "__main__":
    main()
