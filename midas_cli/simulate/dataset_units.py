"""`midas simulate dataset` as units of a batch run (midas_cli/jobs): one unit per trial.

A trial draws everything from (seed, trial), so a unit is the same wherever it runs. Its fingerprint
covers its settings and the midas version; a finished trial whose session folder still exists is not
simulated again (a new one would get a new folder: session folders are never overwritten).
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any, Sequence

from midas_cli import __version__
from midas_cli.jobs.rundir import Unit, fingerprint
from midas_cli.jobs.tasks import task_name
from midas_cli.simulate.trial import TrialConfig, write_trial

TASK = task_name(__name__)  # registered in jobs/tasks.py


def plan_units(configs: Sequence[TrialConfig]) -> list[Unit]:
    units = []
    for config in configs:
        args = {**asdict(config), "out_root": str(Path(config.out_root).expanduser().resolve())}
        units.append(Unit(f"{config.platform} trial {config.trial}", args, fingerprint(TASK, args, __version__)))
    return units


def run_unit(args: dict[str, Any]) -> dict[str, Any]:
    """Write one simulated trial (a unit's ``args``); {path, duration_s, frames, segments}."""
    result = write_trial(TrialConfig(**{**args, "out_root": Path(args["out_root"])}))
    return {"result": result, "outputs": [result["path"]]}
