"""Batch work end to end: a command's units planned, run here or as one SLURM array, waited for and
collected.

A command plans its units (``Unit``: args + input fingerprint) and its options say where they run
(``BatchOptions`` -> ``ExecutorChoice``); ``run_plan`` writes them into a run folder, skips the units
done with the same fingerprint, runs the rest here (``--jobs N``) or submits them as one SLURM array
(one task per unit: ``python -m midas_cli jobs run-unit RUN_DIR --unit K``), waits (unless
``--no-wait``) and returns every unit's result. The caller renders the results, then lists the failed
units (``Outcome.raise_failed``). Nothing here prints: what the user is told goes through a ``Watch``.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ContextManager, Optional, Protocol, Sequence

from midas_cli.errors import ConfigError, UnitsFailedError
from midas_cli.jobs import slurm, status
from midas_cli.jobs.local import run_local
from midas_cli.jobs.options import ExecutorChoice
from midas_cli.jobs.rundir import Plan, RunDir, Unit, fingerprint, now_utc
from midas_cli.jobs.tasks import task_function

RUNS_FOLDER = Path("midas-runs")


class Display(Protocol):
    """The progress display a run advances (the subset of ``rich.progress.Progress`` it uses)."""

    def add_task(self, description: str, total: float | None = ..., **fields: Any) -> Any: ...

    def advance(self, task_id: Any, advance: float = 1) -> None: ...

    def update(self, task_id: Any, **changes: Any) -> None: ...


@dataclass
class Watch:
    """How a run tells its user what happens: ``say`` one line (units skipped, a job submitted, waiting
    stopped), ``display()`` opens the progress display a batch of units advances."""

    say: Callable[[str], None]
    display: Callable[[], ContextManager[Display]]


@dataclass
class Outcome:
    """Every unit's result in plan order (None where it has none), and the failed units' states."""

    run_dir: Optional[Path]  # None: a temporary one, gone
    results: list[Any]
    failed: list[status.UnitStatus]
    submitted: Optional[str] = None  # the SLURM job id when not waited for

    def raise_failed(self, what: str = "units") -> None:
        """UnitsFailedError naming every unit that did not finish (with its error and log), if any;
        ``what``: the units' word in the message (sessions, folds, ...)."""
        if not self.failed:
            return
        parts = []
        for s in self.failed:
            where = f" (log {s.log})" if s.log and s.state == "failed" else ""
            parts.append(f"{s.name}: {s.state}" + (f": {s.error}" if s.error else "") + where)
        kept = f" (run folder {self.run_dir})" if self.run_dir else ""
        error = UnitsFailedError(f"{len(self.failed)} of {len(self.results)} {what} did not finish; the others' "
                                 f"results are kept{kept}: " + "; ".join(parts))
        codes = {s.exit_code for s in self.failed}
        if None not in codes and codes <= {2, 3, 4}:  # every unit failed on a usage/device/data error: say which
            error.exit_code = max(c for c in codes if c is not None)
        raise error


def run_plan(task: str, units: Sequence[Unit], choice: ExecutorChoice, label: str, watch: Watch,
             extra: Optional[dict[str, Any]] = None) -> Outcome:
    """Run ``units`` of ``task`` with ``choice``; ``label`` names the batch on the progress display;
    ``extra`` keyword arguments go to the task function when units run in this process (a progress
    callback). The run folder: ``choice.run_dir``; with slurm by default ``midas-runs/<task>-<key>/``
    here; otherwise a temporary one. No units: nothing is run or written (a plan has one or more)."""
    if not units:
        return Outcome(choice.run_dir, [], [])
    if choice.run_dir is not None:
        return _run_in(RunDir(choice.run_dir), task, units, choice, label, watch, extra)
    if choice.executor == "slurm":
        key = fingerprint(task, sorted(u.name for u in units))  # not the options: a change makes units stale
        return _run_in(RunDir(RUNS_FOLDER / f"{task}-{key}"), task, units, choice, label, watch, extra)
    with tempfile.TemporaryDirectory(prefix=f"midas-{task}-") as tmp:
        outcome = _run_in(RunDir(tmp), task, units, choice, label, watch, extra)
        for failed in outcome.failed:
            failed.log = None  # the temporary run folder goes: the error line says it all
        outcome.run_dir = None
        return outcome


def _run_in(run_dir: RunDir, task: str, units: Sequence[Unit], choice: ExecutorChoice, label: str, watch: Watch,
            extra: Optional[dict[str, Any]]) -> Outcome:
    if choice.executor == "slurm":
        busy = slurm.in_use(run_dir) if (run_dir.path / "submissions.json").exists() else None
        if busy:
            raise ConfigError(f"run folder {run_dir.path} is in use by SLURM job {busy} (still queued or running): "
                              f"wait for it (midas jobs status {run_dir.path}) or cancel it (scancel {busy})")
    plan = run_dir.write_plan(Plan(task, list(units)))
    todo = [u.index for u in plan.units if not run_dir.is_done(u)]
    if len(todo) < len(plan.units):
        watch.say(f"midas: {len(plan.units) - len(todo)} of {len(plan.units)} units done already (same inputs): "
                  f"skipped ({run_dir.path})")
    if todo and choice.executor == "local":
        _run_here(run_dir, task, todo, choice, label, watch, extra)
    elif todo:
        job_id = _submit(run_dir, task, todo, choice, watch)
        if not choice.wait:
            return Outcome(run_dir.path, [], [], submitted=job_id)
        _wait(run_dir, todo, job_id, label, watch)
    found = status.statuses(run_dir)
    results = [(run_dir.read_marker(s.index, "done") or {}).get("result") if s.state == "done" else None
               for s in found]
    return Outcome(run_dir.path, results, [s for s in found if s.state != "done"])


def _run_here(run_dir: RunDir, task: str, todo: list[int], choice: ExecutorChoice, label: str, watch: Watch,
              extra: Optional[dict[str, Any]]) -> None:
    """The local executor: ``todo`` in this process or ``choice.jobs`` workers, a bar per unit done."""
    run_dir.add_submission({"executor": "local", "units": todo, "submitted": now_utc(), "jobs": choice.jobs})
    fn = task_function(task)
    if len(todo) == 1:  # one unit: its own progress (if any) says it all
        run_local(run_dir, todo, fn, 1, **(extra or {}))
        return
    with watch.display() as progress:
        bar = progress.add_task(label, total=len(todo), info="")
        run_local(run_dir, todo, fn, choice.jobs, on_unit=lambda k, ok: progress.advance(bar), **(extra or {}))


def _submit(run_dir: RunDir, task: str, todo: list[int], choice: ExecutorChoice, watch: Watch) -> str:
    """The SLURM executor: ``todo`` as one array job; its id."""
    assert choice.slurm is not None  # ExecutorChoice: always set with slurm
    entry = slurm.submit(run_dir, task, todo, choice.slurm)
    run_dir.add_submission({**entry, "submitted": now_utc()})
    job_id = str(entry["job_id"])
    watch.say(f"midas: submitted SLURM job {job_id}: {len(todo)} array tasks ({entry['script']}); "
              f"follow with: midas jobs status {run_dir.path}")
    return job_id


def _wait(run_dir: RunDir, todo: list[int], job_id: str, label: str, watch: Watch) -> None:
    with watch.display() as progress:
        bar = progress.add_task(label, total=len(todo), info="")

        def update(found: list[status.UnitStatus]) -> None:
            n = status.counts(found)
            progress.update(bar, completed=n["done"] + n["failed"],
                            info=f"queued {n['queued']}, running {n['running']}, failed {n['failed']}")
        try:
            status.wait(run_dir, todo, update)
        except KeyboardInterrupt:
            watch.say(f"midas: stopped waiting; SLURM job {job_id} goes on (midas jobs status {run_dir.path}; "
                      f"scancel {job_id} stops it)")
            raise
