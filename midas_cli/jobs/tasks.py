"""The registry of unit tasks: each task's name (``plan.json``'s ``task``, SLURM's ``midas-<task>`` job
name) and the module that plans and runs its units, named here once.

jobs/ sits below every package that has units, so it names their modules as strings and imports one
only when a unit of its task runs (``task_function``: ``midas jobs run-unit`` on a SLURM node, or a
local run). A units module takes its name from here (``TASK = task_name(__name__)``) and defines
``run_unit(args, **extra) -> {"result": JSON, "outputs": [paths]}``. A new batch task: one line here.
"""

from __future__ import annotations

import importlib

from midas_cli.errors import ConfigError
from midas_cli.jobs.runner import TaskFn

UNIT_MODULES: dict[str, str] = {
    "align": "midas_cli.analysis.align_units",
    "train-fold": "midas_cli.models.cv_units",
    "image-features": "midas_cli.models.image_features_units",
    "extract-handkp": "midas_cli.analysis.handkp_units",
    "ablation-cell": "midas_cli.models.ablation_units",
    "pedals-gt": "midas_cli.analysis.pedal_video.units",
    "simulate-trial": "midas_cli.simulate.dataset_units",
}


def task_name(module: str) -> str:
    """The task whose units ``module`` (a units module's ``__name__``) plans and runs."""
    names = [task for task, path in UNIT_MODULES.items() if path == module]
    if len(names) != 1:
        raise LookupError(f"{module} is not in midas_cli.jobs.tasks.UNIT_MODULES once: add its task there")
    return names[0]


def task_function(task: object) -> TaskFn:
    """The function that runs one unit of ``task`` (read from a run folder: only a registered name
    resolves, anything else is a one-line ConfigError)."""
    module = UNIT_MODULES.get(task) if isinstance(task, str) else None
    if module is None:
        raise ConfigError(f"unknown unit task {task!r} in the run folder (a newer midas wrote it?)")
    run_unit: TaskFn = importlib.import_module(module).run_unit
    return run_unit
