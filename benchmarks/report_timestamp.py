"""BENCHMARKS.md section for the timestamp error of the serial path (bench_timestamp_error.py)."""

from __future__ import annotations

from typing import Any

NAMES = {"emht": "EmHT (trakSTAR, fob://)", "fps": "pedal board (fps://)"}


def _condition(c: dict[str, Any]) -> str:
    load = f"{c['load_processes']} busy loops" if c["load_processes"] else "no added load"
    return load + (f", recorder at nice {c['recorder_nice']}" if c["recorder_nice"] else "")


def _four(f: dict[str, float]) -> str:
    return f"{f['mean_ms']:.2f} / {f['sd_ms']:.2f} / {f['p99_ms']:.2f} / {f['max_ms']:.2f}"


def _verdict(value: float, goal: float) -> str:
    return "yes" if value <= goal else "**no**"


def timestamp_section(r: dict[str, Any]) -> list[str]:
    """The table per condition and stream: raw and fitted error against the goal and the paper."""
    m, raw_goal, fit_goal = r["machine"], r["goal_raw_p99_ms"], r["goal_fitted_p99_ms"]
    lines = ["## 10. Timestamp error of the serial path (`bench_timestamp_error.py`)", "",
             "`midas record` of `" + "`, `".join(r["devices"]) + "`: the trakSTAR and pedal-board emulators on "
             "pseudo-terminals (each in its own process, at nice " f"{r['emulator_nice']}: they stand in for hardware) "
             "log when the write of each record's last byte returned (`devices/send_log.py`); every recorded row is "
             "matched to its record (pedal board by `seq`, trakSTAR by order) and its error is `t_host_ns` − that "
             "time, on the session's clock. *Fitted*: analysis/clockfit.py's times (`align --times fitted`): the "
             "pedal board against `t_device_us`, the trakSTAR against `seq` at 220 Hz (the FOB records carry no "
             f"device time). {r['duration_s'] if 'duration_s' in r else r['conditions'][0]['duration_s']:g} s "
             f"per condition; {r['cores']} cores, {m['cpu_model']}, {m['date_utc']}; the load average includes "
             "the other users of this shared machine.", "",
             f"Goal (issue 26): raw p99 ≤ {raw_goal:g} ms, fitted p99 ≤ {fit_goal:g} ms. Errors in ms: mean / sd "
             "(signed), p99 / max of |error|.", "",
             "| condition | load 1 min | stream | rows (never sent) | raw mean / sd / p99 / max | raw p99 ≤ "
             f"{raw_goal:g} | fitted − sent mean / sd / p99 / max | fitted about the device clock p99 | ≤ {fit_goal:g} "
             "| emulator late p50 / p99 |", "|---|---|---|---|---|---|---|---|---|---|"]
    for c in r["conditions"]:
        load = "–".join(f"{x:g}" for x in c["load_average_before_after"])
        for name, s in c["streams"].items():
            about = s["fitted_vs_due_less_mean"]["p99_ms"]
            late = s["emulator_late"]
            lines.append(f"| {_condition(c)} | {load} | {NAMES.get(name, name)} | {s['rows']} ({s['missing']}) | "
                         f"{_four(s['raw'])} | {_verdict(s['raw']['p99_ms'], raw_goal)} | {_four(s['fitted'])} | "
                         f"{about:.2f} | {_verdict(about, fit_goal)} | {late['p50_ms']:.2f} / {late['p99_ms']:.2f} |")
        bare = c["bare_fps_reader"]
        lines.append(f"| {_condition(c)} | {load} | pedal board, bare reader (no midas) | {bare['rows']} | "
                     f"{_four(bare['raw'])} | {_verdict(bare['raw']['p99_ms'], raw_goal)} | — | — | — | — |")
    lines += ["", "*Bare reader*: a process at nice 0 that only waits in select, reads and stamps each pedal line "
              "(no decoding into rows, no file, no bookkeeping), run right after the recording with the same load: "
              "what the kernel's pty path and the scheduler give on this machine at that moment. The difference "
              "between it and midas's pedal row is midas's own share. *Never sent*: samples the emulated board "
              "skipped because its transmit buffer was full (the host had not read for tens of ms), as a real "
              "board does; they are not rows and not in the error figures."]
    paper = ", ".join(f"{k} {v:g} ms" for k, v in r["paper_mean_ms"].items())
    return lines + ["", f"* The paper (Appendix A.1, Table `tab:latencies`) reports mean source-to-disk latency ({paper}) "
                    "and no timestamp error: its figures include the write to disk; the raw mean here is the device "
                    "-> host-stamp part alone (stamp -> disk is section 1's latency).",
                    "* *Fitted − sent* carries how late the emulator itself was (the fit follows the device clock, "
                    "i.e. when a record was due, and an emulated device, unlike firmware, sends late when its process "
                    "waits for a CPU); *about the device clock* is fitted − due less its mean (a constant delay no fit "
                    "can see): what the fit leaves on a device that sends on time.",
                    "* Errors can be slightly negative: the send time is taken after the emulator's write returned, and "
                    "a reader on the other core may stamp first.", ""]
