"""`--executor local|slurm` for the commands that loop over units (sessions, folds): the shared options,
the registry of unit tasks, and running a plan to the end with a progress line.

A command plans its units (``Unit``: args + input fingerprint), then ``run_plan`` writes them into a run
folder, skips the units done with the same fingerprint, runs the rest here (``--jobs N``) or submits
them as one SLURM array (one task per unit: ``python -m midas_cli jobs run-unit RUN_DIR --unit K``),
waits (unless ``--no-wait``) and returns every unit's result. Failed units are listed by the caller
after it has rendered the others' results (``raise_failed``).
"""

from __future__ import annotations

import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Optional, Sequence

import typer
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from midas_cli.commands.common import error_line
from midas_cli.commands.progress import progress_display, progress_interval_s
from midas_cli.errors import ConfigError, UnitsFailedError

PANEL = "Executor"
EXECUTORS = ("local", "slurm")
RUNS_FOLDER = Path("midas-runs")

EXECUTOR_OPT = typer.Option("local", "--executor", rich_help_panel=PANEL, help="local (this machine, --jobs "
                            "workers) or slurm (one SLURM array task per unit; settings from --slurm-* or the "
                            "\\[slurm] section of the config file).")
JOBS_OPT = typer.Option(1, "--jobs", "-j", rich_help_panel=PANEL, help="Local executor: units run in parallel "
                        "(worker processes).")
RUN_DIR_OPT = typer.Option(None, "--run-dir", rich_help_panel=PANEL, file_okay=False, help="Run folder: plan, "
                           "per-unit done/failed markers and logs; a re-run skips the units done with the same "
                           "inputs (`midas jobs status RUN_DIR`). Default with slurm: midas-runs/<task>-<key>/ "
                           "here; local: a temporary folder.")
NO_WAIT_OPT = typer.Option(False, "--no-wait", rich_help_panel=PANEL, help="slurm: submit, print the run folder "
                           "and return at once (follow it with `midas jobs status`; the same command run again "
                           "afterwards skips the done units and prints or writes the collected results).")
PARTITION_OPT = typer.Option(None, "--slurm-partition", rich_help_panel=PANEL, help="SLURM partition.")
TIME_OPT = typer.Option(None, "--slurm-time", rich_help_panel=PANEL, help="Time limit per unit, e.g. 01:00:00.")
MEM_OPT = typer.Option(None, "--slurm-mem", rich_help_panel=PANEL, help="Memory per unit, e.g. 8G.")
GPUS_OPT = typer.Option(None, "--slurm-gpus", rich_help_panel=PANEL, help="GPUs per unit (--gres=gpu:N).")
PARALLEL_OPT = typer.Option(None, "--slurm-array-parallelism", rich_help_panel=PANEL, help="Most array tasks "
                            "running at once.")


@dataclass
class ExecutorChoice:
    executor: str = "local"
    jobs: int = 1
    run_dir: Optional[Path] = None
    wait: bool = True
    slurm: Any = None  # jobs.slurm.SlurmSettings with --executor slurm: the flags over the config's [slurm]


def executor_choice(executor: str, jobs: int, run_dir: Optional[Path], no_wait: bool, partition: Optional[str],
                    time: Optional[str], mem: Optional[str], gpus: Optional[int],
                    parallelism: Optional[int]) -> ExecutorChoice:
    """The executor options of a command, checked (one-line ConfigError on a bad one), with slurm the
    settings too (flags and the config's ``[slurm]``, in SLURM's grammar) before any work starts."""
    if executor not in EXECUTORS:
        raise ConfigError(f"--executor must be {' or '.join(EXECUTORS)}, got {executor!r}")
    if jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {jobs}")
    flags = {"partition": partition, "time": time, "mem": mem, "gpus": gpus, "array_parallelism": parallelism}
    if executor == "local":
        given = [f"--slurm-{k.replace('_', '-')}" for k, v in flags.items() if v is not None]
        if no_wait or given:
            raise ConfigError(f"{(['--no-wait'] if no_wait else given)[0]} needs --executor slurm")
        return ExecutorChoice(executor, jobs, run_dir, not no_wait)
    if jobs != 1:
        raise ConfigError("--jobs is for --executor local; SLURM runs every unit as its own task "
                          "(--slurm-array-parallelism caps how many at once)")
    from midas_cli import config
    from midas_cli.jobs.slurm import SlurmSettings

    return ExecutorChoice(executor, jobs, run_dir, not no_wait, SlurmSettings.merged(flags, config.section("slurm")))


def task_function(task: str) -> Callable[..., dict[str, Any]]:
    """The library function that runs one unit of ``task`` (plan.json's task)."""
    if task == "align":
        from midas_cli.analysis.align_units import run_unit
        return run_unit
    if task == "train-fold":
        from midas_cli.models.cv_units import run_unit
        return run_unit
    if task == "image-features":
        from midas_cli.models.image_features_units import run_unit
        return run_unit
    if task == "extract-handkp":
        from midas_cli.analysis.handkp_units import run_unit
        return run_unit
    if task == "ablation-cell":
        from midas_cli.models.ablation_units import run_unit
        return run_unit
    if task == "pedals-gt":
        from midas_cli.analysis.pedal_video.units import run_unit
        return run_unit
    if task == "simulate-trial":
        from midas_cli.simulate.dataset_units import run_unit
        return run_unit
    raise ConfigError(f"unknown unit task {task!r} in the run folder (a newer midas wrote it?)")


@dataclass
class Outcome:
    """Every unit's result in plan order (None where it has none), and the failed units' states."""

    run_dir: Optional[Path]  # None: a temporary one, gone
    results: list[Any]
    failed: list[Any]
    submitted: Optional[str] = None  # the SLURM job id when not waited for


def run_plan(task: str, units: Sequence[Any], choice: ExecutorChoice, label: str,
             extra: Optional[dict[str, Any]] = None, progress: Any = None) -> Outcome:
    """Run ``units`` of ``task`` with ``choice``; ``extra`` keyword arguments go to the task function when
    units run in this process (a progress callback); ``progress``: the caller's open progress display."""
    from midas_cli.jobs.rundir import RunDir, fingerprint

    progress_interval_s()  # a bad MIDAS_PROGRESS_INTERVAL_S is a usage error before any work, shown or not
    if choice.run_dir is not None:
        return _run_in(RunDir(choice.run_dir), task, units, choice, label, extra, progress)
    if choice.executor == "slurm":
        key = fingerprint(task, sorted(u.name for u in units))  # not the options: a change makes units stale
        return _run_in(RunDir(RUNS_FOLDER / f"{task}-{key}"), task, units, choice, label, extra, progress)
    with tempfile.TemporaryDirectory(prefix=f"midas-{task}-") as tmp:
        outcome = _run_in(RunDir(tmp), task, units, choice, label, extra, progress)
        for status in outcome.failed:
            status.log = None  # the temporary run folder goes: the error line says it all
        outcome.run_dir = None
        return outcome


def unit_progress():
    """The progress display of a batch run (what, bar, n/total, info, elapsed, ETA); every task needs an
    ``info`` field."""
    return progress_display(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                            TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TimeRemainingColumn())


@contextmanager
def _display(given: Any) -> Iterator[Any]:
    if given is not None:
        yield given
        return
    with unit_progress() as progress:
        yield progress


def _run_in(run_dir, task: str, units: Sequence[Any], choice: ExecutorChoice, label: str,
            extra: Optional[dict[str, Any]], shown: Any) -> Outcome:
    from midas_cli.jobs import slurm, status
    from midas_cli.jobs.local import run_local
    from midas_cli.jobs.rundir import Plan, now_utc

    if choice.executor == "slurm":
        busy = slurm.in_use(run_dir) if (run_dir.path / "submissions.json").exists() else None
        if busy:
            raise ConfigError(f"run folder {run_dir.path} is in use by SLURM job {busy} (still queued or running): "
                              f"wait for it (midas jobs status {run_dir.path}) or cancel it (scancel {busy})")
    plan = run_dir.write_plan(Plan(task, list(units)))
    todo = [u.index for u in plan.units if not run_dir.is_done(u)]
    if len(todo) < len(plan.units):
        error_line(f"midas: {len(plan.units) - len(todo)} of {len(plan.units)} units done already (same inputs): "
                   f"skipped ({run_dir.path})")
    job_id = None
    if todo and choice.executor == "local":
        run_dir.add_submission({"executor": "local", "units": todo, "submitted": now_utc(), "jobs": choice.jobs})
        fn = task_function(task)
        if len(todo) == 1:  # one unit: its own progress (if any) says it all
            run_local(run_dir, todo, fn, 1, **(extra or {}))
        else:
            with _display(shown) as progress:
                bar = progress.add_task(label, total=len(todo), info="")
                run_local(run_dir, todo, fn, choice.jobs, on_unit=lambda k, ok: progress.advance(bar), **(extra or {}))
    elif todo:
        entry = slurm.submit(run_dir, task, todo, choice.slurm)
        run_dir.add_submission({**entry, "submitted": now_utc()})
        job_id = entry["job_id"]
        error_line(f"midas: submitted SLURM job {job_id}: {len(todo)} array tasks ({entry['script']}); "
                   f"follow with: midas jobs status {run_dir.path}")
        if not choice.wait:
            return Outcome(run_dir.path, [], [], submitted=job_id)
        _wait(run_dir, todo, job_id, label, shown)
    found = status.statuses(run_dir)
    results = [(run_dir.read_marker(s.index, "done") or {}).get("result") if s.state == "done" else None
               for s in found]
    return Outcome(run_dir.path, results, [s for s in found if s.state != "done"])


def _wait(run_dir, todo: list[int], job_id: str, label: str, shown: Any) -> None:
    from midas_cli.jobs import status

    with _display(shown) as progress:
        bar = progress.add_task(label, total=len(todo), info="")

        def update(found) -> None:
            n = status.counts(found)
            progress.update(bar, completed=n["done"] + n["failed"],
                            info=f"queued {n['queued']}, running {n['running']}, failed {n['failed']}")
        try:
            status.wait(run_dir, todo, update)
        except KeyboardInterrupt:
            error_line(f"midas: stopped waiting; SLURM job {job_id} goes on (midas jobs status {run_dir.path}; "
                       f"scancel {job_id} stops it)")
            raise


def raise_failed(outcome: Outcome, what: str = "units") -> None:
    """UnitsFailedError naming every unit that did not finish (with its error and log), if any."""
    if not outcome.failed:
        return
    parts = []
    for s in outcome.failed:
        where = f" (log {s.log})" if s.log and s.state == "failed" else ""
        parts.append(f"{s.name}: {s.state}" + (f": {s.error}" if s.error else "") + where)
    kept = f" (run folder {outcome.run_dir})" if outcome.run_dir else ""
    error = UnitsFailedError(f"{len(outcome.failed)} of {len(outcome.results)} {what} did not finish; the others' "
                             f"results are kept{kept}: " + "; ".join(parts))
    codes = {s.exit_code for s in outcome.failed}
    if None not in codes and codes <= {2, 3, 4}:  # every unit failed on a usage/device/data error: say which
        error.exit_code = max(codes)
    raise error


def submitted_line(outcome: Outcome) -> None:
    """--no-wait: the run folder on stdout (scripts take it), the job on stderr."""
    error_line(f"midas: SLURM job {outcome.submitted} submitted; not waiting (midas jobs status {outcome.run_dir})")
    print(outcome.run_dir)
