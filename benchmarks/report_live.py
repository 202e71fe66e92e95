"""BENCHMARKS.md: live gesture recognition (issue 28), from results/live_gestures.json
(bench_live_gestures.py: the cost per frame) and results/live_record.json (bench_live_record.py: the rig
recording with and without the model)."""

from __future__ import annotations

from typing import Any

GOAL_FRAME_P99_MS, GOAL_RECORD_P99_MS, GOAL_CPU_PERCENT = 20.0, 5.0, 40.0


def _per_frame(report: dict[str, Any]) -> list[str]:
    out = ["### Cost per frame (`bench_live_gestures.py`)", "",
           f"Run {report['machine']['date_utc']}, load {report.get('load_average_1min_before')} before, one torch "
           f"thread; a {report['seconds']:g}-s simulated session's EmHT rows fed in {report['chunk_ms']:g} ms chunks.",
           "", "| causal model | rate | frames | LiveFeed per frame p50 / p99 / max (ms) | model step alone p50 / p99 (ms) "
           "| state (floats) | decoding step alone p50 / p99 (ms) | goal p99 <= 20 ms |", "|---|---|---|---|---|---|---|---|"]
    for name, m in report["models"].items():
        live, step = m["live"]["per_frame"], m["model_step"]
        decoding = m.get("decoding_step")  # runs from before the live decoding (2026-11-27) have none
        decoded = "—" if decoding is None else (f"{decoding['p50_ms']} / {decoding['p99_ms']} "
                                                f"(minimum {decoding['min_segment_frames']} frames)")
        ok = "yes" if live["p99_ms"] <= GOAL_FRAME_P99_MS else "no"
        out.append(f"| {name} | {m['rate_hz']:g} Hz | {m['live']['frames']} | {live['p50_ms']} / {live['p99_ms']} / "
                   f"{live['max_ms']} | {step['p50_ms']} / {step['p99_ms']} | {step['state_floats']} | {decoded} | {ok} |")
    return out + [""]


def _cpu(run: dict[str, Any]) -> tuple[float, str]:
    """Total steady CPU (% of one core) and the per-process split, largest first."""
    parts = dict(run["steady_cpu_percent_of_one_core"]["percent"])
    total = float(parts.pop("total"))
    split = ", ".join(f"{k} {float(v):.1f}" for k, v in sorted(parts.items(), key=lambda kv: -float(kv[1])) if v)
    return total, split


def _recording(report: dict[str, Any]) -> list[str]:
    out = ["### Recording with the model (`bench_live_record.py`)", "",
           f"{report['model']}; the full rig on emulators (EmHT 4 x 220 Hz, FPS 9 ch x 850 Hz, video and HandKP 30 Hz). "
           "CPU: each process over the middle of the recording, % of one core. Recognition latency: `t_pred_ns - "
           "t_host_ns` of each `gestures_live` row (the frame's time to its prediction, including the wait for the "
           "samples after the frame that its features need).", "",
           "| live model | load before–after | CPU total (% of a core) | CPU per process | worst stream p99 (ms) | "
           "sent − recorded + dropped | recognition frames | recognition latency p50 / p99 (ms) | skipped frames |",
           "|---|---|---|---|---|---|---|---|---|"]
    for run in report["runs"]:
        total, split = _cpu(run)
        worst = max(s["latency_ms"]["p99"] for s in run["streams"].values())
        lost = sum(max(0, s.get("sent_minus_recorded") or 0) + (s["queue_dropped"] or 0) for s in run["streams"].values())
        rec = run.get("recognition") or {}
        lat = rec.get("latency") or {}
        live = (rec.get("manifest") or {}).get("live_model") or {}
        load = "–".join(f"{x:g}" for x in run["load_average_before_after"])
        latency = f"{lat['p50_ms']} / {lat['p99_ms']}" if "p50_ms" in lat else "—"
        out.append(f"| {'on' if run['live_model'] else 'off'} | {load} | {total:.1f} | {split} | {worst:g} | {lost} | "
                   f"{lat.get('frames', '—') if run['live_model'] else '—'} | "
                   f"{latency} | "
                   f"{live.get('frames_skipped', '—') if run['live_model'] else '—'} |")
    return out + ["", *_verdict(report)]


def _verdict(report: dict[str, Any]) -> list[str]:
    """Issue 28's recording goals against the runs with the model."""
    on = [run for run in report["runs"] if run["live_model"]]
    off = [run for run in report["runs"] if not run["live_model"]]
    if not on:
        return []
    p99 = max(max(s["latency_ms"]["p99"] for s in run["streams"].values()) for run in on)
    cpu = max(_cpu(run)[0] for run in on)
    base = f"; without the model: {max(_cpu(run)[0] for run in off):.1f} %" if off else ""
    worker = max(float(run["steady_cpu_percent_of_one_core"]["percent"].get("worker gestures_live", 0)) for run in on)
    runs = report["runs"]  # off and on alternate: each on run against the off run just before it
    added = [_cpu(b)[0] - _cpu(a)[0] for a, b in zip(runs, runs[1:]) if not a["live_model"] and b["live_model"]]
    if added:
        base += f"; the model added {', '.join(f'{x:+.1f}' for x in added)} points to the run just before it"
    return [f"Goals (issue 28) with the model: recording p99 <= {GOAL_RECORD_P99_MS:g} ms: "
            f"{'met' if p99 <= GOAL_RECORD_P99_MS else 'not met'} (worst stream {p99:g} ms); recorder + workers + "
            f"recognition <= {GOAL_CPU_PERCENT:g} % of one core: {'met' if cpu <= GOAL_CPU_PERCENT else 'not met'} "
            f"(worst run {cpu:.1f} %{base}; the recognition worker itself {worker:.1f} %). The recognition latency is mostly "
            "waiting: a frame's features need the samples after it (velocities by central differences, as training "
            "computed them), and the device workers hand their rows over every 50 ms (`record/feed.py`), so a frame "
            "is predicted one video period or more after its time; the computation itself is the per-frame table "
            "above." + (f" Without the model the same recording took {min(_cpu(r)[0] for r in off):.1f}–"
                        f"{max(_cpu(r)[0] for r in off):.1f} % in these runs minutes apart (a shared machine): "
                        "compare each on run with the off run before it." if len(off) > 1 else ""), ""]


def live_section(per_frame: dict[str, Any] | None, recording: dict[str, Any] | None) -> list[str]:
    """Section 11: live gesture recognition, whichever of its two results exist."""
    out = ["## 11. Live gesture recognition (`bench_live_gestures.py`, `bench_live_record.py`)", ""]
    out += _per_frame(per_frame) if per_frame else ["Cost per frame: no results yet (run bench_live_gestures.py).", ""]
    out += _recording(recording) if recording else ["Recording with the model: no results yet (run bench_live_record.py).",
                                                    ""]
    return out
