"""Each unit's state, read from the run folder's markers and (for SLURM submissions) the queue.

States: ``pending`` (never submitted, or its inputs changed and it waits for a re-run), ``queued``
(in the SLURM queue, not started), ``running``, ``done`` (with the plan's fingerprint), ``stale``
(done, but with other inputs or options, or an output gone), ``failed`` (with the last error line and
the log). A unit whose process or SLURM task ended without writing done or failed (killed: time or
memory limit, node failure, scancel) is failed too, with the log's last error line.
"""

from __future__ import annotations

import socket
import time
from dataclasses import asdict, dataclass
from typing import Any, Callable, Sequence

from midas_cli.jobs import slurm
from midas_cli.jobs.rundir import RunDir, Unit, log_error_line
from midas_cli.processes import process_alive

TERMINAL = ("done", "failed")
STATES = ("pending", "queued", "running", "done", "stale", "failed")


@dataclass
class UnitStatus:
    index: int
    name: str
    state: str
    error: str | None = None
    log: str | None = None
    job: str | None = None
    host: str | None = None
    seconds: float | None = None
    exit_code: int | None = None  # a failed unit's error kind (midas exit codes); None: killed, never ran

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def _job_tasks(run_dir: RunDir) -> tuple[dict[int, tuple[str, str]], dict[int, str]]:
    """(unit -> (job id, queue state) for units in the queue now, unit -> job id of the latest SLURM
    submission that ran it). The queue is asked before any marker is read: a task that ends in between
    has written its marker by the time it leaves the queue."""
    in_queue: dict[int, tuple[str, str]] = {}
    submitted: dict[int, str] = {}
    asked: dict[str, dict[int, str] | None] = {}
    for entry in run_dir.submissions():
        if entry.get("executor") != "slurm":
            for k in entry.get("units", []):
                submitted.pop(k, None)
            continue
        job = str(entry.get("job_id"))
        for k in entry.get("units", []):
            submitted[k] = job
    for k, job in submitted.items():
        if job not in asked:
            asked[job] = slurm.queued(job)
        tasks = asked[job]
        if tasks is None:  # the queue cannot be asked: assume the task is still there
            in_queue[k] = (job, "UNKNOWN")
        elif k in tasks:
            in_queue[k] = (job, tasks[k])
    return in_queue, submitted


def unit_status(run_dir: RunDir, unit: Unit, in_queue: dict[int, tuple[str, str]], submitted: dict[int, str]) -> UnitStatus:
    k = unit.index
    log = str(run_dir.log(k))
    job = submitted.get(k)
    status = UnitStatus(k, unit.name, "pending", log=log, job=job)
    done = run_dir.read_marker(k, "done")
    if done is not None:
        status.host, status.seconds = done.get("host"), done.get("seconds")
        status.state = "done" if run_dir.is_done(unit) else "stale"
        if status.state == "done" or k not in in_queue:
            return status
    failed = run_dir.read_marker(k, "failed")
    if failed is not None and k not in in_queue:
        status.state, status.error, status.host = "failed", failed.get("error"), failed.get("host")
        status.exit_code = failed.get("exit_code")
        status.log = failed.get("log") or log
        return status
    running = run_dir.read_marker(k, "running")
    if k in in_queue:
        status.state = "running" if running is not None or in_queue[k][1] in ("RUNNING", "COMPLETING") else "queued"
        status.host = (running or {}).get("host")
        return status
    if running is not None:
        status.host = running.get("host")
        if running.get("job_id"):  # a SLURM task that left the queue without a result
            status.state = "failed"
            status.error = ("the SLURM task ended without a result (time or memory limit, node failure, scancel?): "
                            + (log_error_line(run_dir.log(k)) or "its log says nothing"))
        elif running.get("host") == socket.gethostname() and not process_alive(int(running.get("pid", 0))):
            status.state, status.error = "failed", "its process died without a result (killed?)"
        else:
            status.state = "running"
        return status
    if job is not None and done is None:  # submitted, left the queue, never started or never marked
        status.state = "failed"
        status.error = ("the SLURM task ended without starting the unit: "
                        + (log_error_line(run_dir.log(k)) or "no log (cancelled before it ran?)"))
    return status


def statuses(run_dir: RunDir, indices: Sequence[int] | None = None) -> list[UnitStatus]:
    plan = run_dir.read_plan()
    in_queue, submitted = _job_tasks(run_dir)
    wanted = set(range(len(plan.units)) if indices is None else indices)
    return [unit_status(run_dir, u, in_queue, submitted) for u in plan.units if u.index in wanted]


def counts(found: Sequence[UnitStatus]) -> dict[str, int]:
    return {state: sum(1 for s in found if s.state == state) for state in STATES}


def wait(run_dir: RunDir, indices: Sequence[int], on_update: Callable[[list[UnitStatus]], None] | None = None,
         poll_s: float = 1.0) -> list[UnitStatus]:
    """Poll until every unit in ``indices`` is done or failed; returns their final states."""
    while True:
        found = statuses(run_dir, indices)
        if on_update is not None:
            on_update(found)
        if all(s.state in TERMINAL for s in found):
            return found
        time.sleep(poll_s)
