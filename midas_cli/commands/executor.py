"""`--executor local|slurm` for the commands that loop over units (sessions, folds): the executor options,
declared once (``@batch_command``), and the terminal's view of a batch run (``jobs/batch.py`` does the
work: plan, run here or on SLURM, wait, collect).

A batch command is decorated with ``@batch_command`` (below ``@app.command()``) and takes
``batch: BatchOptions`` as its last parameter: the decorator adds the nine options of the "Executor"
help panel to its signature and hands them over as that one object. The command checks them
(``batch.choice()``), plans its units, calls ``run_plan`` here, renders the results and ends with
``outcome.raise_failed(...)`` (the units that did not finish, in one error).
"""

from __future__ import annotations

from contextlib import nullcontext
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Optional, Sequence

import typer
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from midas_cli.commands.common import error_line, print_json
from midas_cli.commands.options import keyword_options, option_group
from midas_cli.commands.progress import progress_display, progress_interval_s
from midas_cli.jobs.options import BatchOptions, ExecutorChoice

if TYPE_CHECKING:
    from midas_cli.jobs.batch import Display, Outcome
    from midas_cli.jobs.rundir import Unit

Steps = Callable[["Display"], Callable[..., None]]  # open display -> a unit's progress callback

PANEL = "Executor"

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

# The executor options as parameters of a command (names: the fields of jobs.options.BatchOptions), in
# the order of the help's "Executor" panel.
BATCH_PARAMETERS = keyword_options(
    ("executor", EXECUTOR_OPT, str), ("jobs", JOBS_OPT, int), ("run_dir", RUN_DIR_OPT, Optional[Path]),
    ("no_wait", NO_WAIT_OPT, bool), ("slurm_partition", PARTITION_OPT, Optional[str]),
    ("slurm_time", TIME_OPT, Optional[str]), ("slurm_mem", MEM_OPT, Optional[str]),
    ("slurm_gpus", GPUS_OPT, Optional[int]), ("slurm_array_parallelism", PARALLEL_OPT, Optional[int]))

# Declares a batch command: its signature gets the executor options after its own, and it is called
# with them as one ``batch: BatchOptions`` argument.
batch_command = option_group("batch", BatchOptions, BATCH_PARAMETERS)


def run_plan(task: str, units: Sequence[Unit], choice: ExecutorChoice, label: str,
             steps: Optional[Steps] = None) -> Outcome:
    """``jobs.batch.run_plan`` in this terminal: its lines on stderr, its bar (``label``) on a progress
    display. ``steps``: the callback of a unit run in this process, made on the open display (a bar of
    its frames or epochs). With --no-wait the run folder is printed on stdout (after the display is
    gone) and the outcome has ``submitted`` set: the command returns without results."""
    from midas_cli.jobs.batch import Watch
    from midas_cli.jobs.batch import run_plan as run

    progress_interval_s()  # a bad MIDAS_PROGRESS_INTERVAL_S is a usage error before any work, shown or not
    if steps is None:  # a display only when the batch needs its bar (several units, or waiting for SLURM)
        outcome = run(task, units, choice, label, Watch(error_line, unit_progress))
    else:
        with unit_progress() as display:
            extra = {"progress": steps(display)} if choice.in_process else None
            outcome = run(task, units, choice, label, Watch(error_line, lambda: nullcontext(display)), extra)
    if outcome.submitted:
        error_line(f"midas: SLURM job {outcome.submitted} submitted; not waiting (midas jobs status {outcome.run_dir})")
        print(outcome.run_dir)  # on stdout: scripts take it
    return outcome


def counted(description: str) -> Steps:
    """``steps`` for units that report ``progress(done, total)`` (a video's frames): one bar."""
    def attach(display: Display) -> Callable[[int, int], None]:
        bar = display.add_task(description, total=None, info="")
        return lambda done, total: display.update(bar, completed=done, total=total or None)
    return attach


def shown_results(outcome: Outcome, as_json: bool, single: bool) -> list[Any]:
    """The units' results for a command to render as lines; with --json they are printed here instead
    (one object when the command was given one input) and nothing is left to render."""
    results = [r for r in outcome.results if r is not None]
    if not as_json:
        return results
    print_json(results[0] if single and results else results)
    return []


def unit_progress():
    """The progress display of a batch run (what, bar, n/total, info, elapsed, ETA); every task needs an
    ``info`` field."""
    return progress_display(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                            TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TimeRemainingColumn())
