"""`midas jobs status|run-unit`: the units of a batch run folder (--executor local|slurm)."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from midas_cli.commands.common import error_line, out, print_json
from midas_cli.commands.options import JSON_OPTION

app = typer.Typer(help="Follow batch runs (--executor local|slurm): each unit's state, log and error.",
                  no_args_is_help=True)

RUN_DIR_ARG = typer.Argument(..., help="Run folder (printed by the command that submitted it; --run-dir).",
                             file_okay=False)


@app.command()
def status(
    run_dir: Path = RUN_DIR_ARG,
    as_json: bool = JSON_OPTION,
) -> None:
    """List a run folder's units: pending, queued, running, done, stale or failed.

    A failed unit shows its log file and the last error line; a unit whose SLURM task ended without a
    result (time or memory limit, scancel) counts as failed. Re-running the command that made the run
    folder (same --run-dir) runs the units that are not done and skips the others.

    Example: midas jobs status midas-runs/align-3f2a9c0d1e2b4a5c
    """
    from midas_cli.jobs.rundir import RunDir
    from midas_cli.jobs.status import counts, statuses

    folder = RunDir(run_dir)
    plan = folder.read_plan()
    found = statuses(folder)
    jobs = sorted({str(e["job_id"]) for e in folder.submissions() if e.get("job_id")})
    if as_json:
        print_json({"run_dir": str(folder.path), "task": plan.task, "slurm_jobs": jobs, "counts": counts(found),
                    "units": [s.to_json() for s in found]})
        return
    table = Table("unit", "name", "state", "host", "seconds", "error / log", header_style="bold")
    for s in found:
        detail = f"{s.error}\n{s.log}" if s.state == "failed" else ""
        table.add_row(str(s.index), s.name, s.state, s.host or "", f"{s.seconds:.1f}" if s.seconds else "", detail)
    out.print(table)
    summary = ", ".join(f"{n} {state}" for state, n in counts(found).items() if n)
    error_line(f"midas: {plan.task}: {summary} ({len(found)} units; SLURM jobs: {', '.join(jobs) or 'none'})")


@app.command("run-unit", hidden=True)
def run_unit_command(
    run_dir: Path = RUN_DIR_ARG,
    unit: int = typer.Option(..., "--unit", help="Unit index (a SLURM array task id)."),
    force: bool = typer.Option(False, "--force", help="Run it even when it is done with the same inputs."),
) -> None:
    """Run one unit of a run folder (what each SLURM array task runs).

    Example: midas jobs run-unit midas-runs/align-3f2a9c0d1e2b4a5c --unit 3
    """
    from midas_cli.jobs.rundir import RunDir
    from midas_cli.jobs.runner import run_unit
    from midas_cli.jobs.slurm import is_slurm_task
    from midas_cli.jobs.tasks import task_function

    folder = RunDir(run_dir)
    plan = folder.read_plan()
    done = run_unit(folder, unit, task_function(plan.task), log_to_file=not is_slurm_task(), force=force)
    error_line(f"midas: unit {unit} ({done.get('name', '')}) done")
