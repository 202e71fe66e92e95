"""BENCHMARKS.md section: `midas align` through the executors, from results/executor.json; used by report.py."""

from __future__ import annotations

METHOD = (
    "`bench_executor.py` writes sessions with every stream at full rate (`bench_align.write_session`), then "
    "aligns all of them three ways, each with a fresh run folder: `--jobs 1`, `--jobs 2` (worker processes, "
    "spawned) and `--executor slurm` on a one-node SLURM started for the run (this machine as controller and "
    "only compute node, its {cpus} CPUs as slots; the tests' cluster, `tests/helpers/slurm_fixture.py`). "
    "Wall = the whole `midas align` command, submission and waiting included. **Unit** = a unit's own time "
    "in its done marker (inside the unit, after the process's imports). **Overhead per unit** = wall × slots "
    "/ units − unit: what each unit costs beyond its work. **Task start-up** = `midas jobs run-unit` on a "
    "unit already done (interpreter, imports, plan read, skip), the floor of any SLURM task."
)


def executor_section(r: dict) -> list[str]:
    cpus = r["machine"]["cpus"]
    out = ["## Executors: align on this machine and through SLURM (`bench_executor.py`)", "",
           METHOD.format(cpus=cpus), "",
           "| sessions × length | executor | slots | wall s | sessions / hour | unit s | overhead / unit s | "
           "load 1 min |", "|---|---|---|---|---|---|---|---|"]
    for run in r["runs"]:
        for m in run["modes"]:
            load = "–".join(f"{v:g}" for v in m["load_1min_before_after"])
            out.append(f"| {run['sessions']} × {run['session_minutes']:g} min | {m['mode']} | {m['slots']} | "
                       f"{m['wall_s']:g} | {m['sessions_per_hour']:,} | {m['unit_mean_s']:g} | "
                       f"{m['overhead_per_unit_s']:g} | {load} |")
    out.append("")
    for run in r["runs"]:
        p = run["projection"]
        out.append(f"* {run['sessions']} × {run['session_minutes']:g} min: SLURM task start-up "
                   f"{run['task_startup_s']:g} s; projection for {p['nodes']} nodes × {p['cores_per_node']} cores "
                   f"(one unit per core, {p['unit_s']:g} s per unit as measured here): "
                   f"{p['sessions_per_hour']:,} sessions / hour, if the controller and the shared file system "
                   "keep up.")
    out += ["* **Reading.** `midas align` is fast (a 20-minute session: well under a second of work), so "
            "what a unit costs elsewhere dominates: spawning `--jobs 2` workers (each imports numpy and "
            "midas) costs more than it saves on these sizes, and a SLURM task costs ~3 s of its slot, about "
            "0.6 s of it the interpreter and imports and the rest SLURM launching and ending the task "
            "(slurmd, slurmstepd, completion messages; `sched/builtin`). On one node SLURM therefore aligns "
            "~2,400 sessions an hour against tens of thousands locally; it pays off where the node count "
            "multiplies the slots, or where units are long (`train gestures --fold all` folds and ablation "
            "cells take minutes, pedal ground truth about video length / 5). The 100-node figure is an upper "
            "bound, not a measurement: it means about 1,100 task starts a second, which a SLURM controller "
            "is unlikely to sustain (not measured here: one node), so the controller and the shared file "
            "system, not the nodes, would set the pace; several sessions per task (not implemented) would be "
            "the next step for short units.", ""]
    folds = r.get("folds")
    if folds:
        out += ["", f"Training folds: `midas train gestures --split loto --fold all --epochs {folds['epochs']}` "
                f"(MS-TCN++, one unit per fold) on {folds['trials']} simulated Raven-II trials of "
                f"{folds['trial_seconds']:g} s:", "",
                "| executor | slots | folds | wall s | folds / hour | unit s | overhead / unit s | load 1 min |",
                "|---|---|---|---|---|---|---|---|"]
        for m in folds["modes"]:
            load = "–".join(f"{v:g}" for v in m["load_1min_before_after"])
            out.append(f"| {m['mode']} | {m['slots']} | {m['units']} | {m['wall_s']:g} | {m['folds_per_hour']:,} | "
                       f"{m['unit_mean_s']:g} | {m['overhead_per_unit_s']:g} | {load} |")
        out += ["", "A fold is long next to a task's start-up, so SLURM's per-unit cost matters far less than for "
                "align; 2 workers on 2 cores share them with torch's own threads. Pedal ground truth per hour "
                "is not measured here (simulated datasets carry no console video; `bench_pedal_gt.py` times "
                "one video).", ""]
    return out
