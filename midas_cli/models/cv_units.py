"""`midas train gestures --fold all` as units of a batch run (midas_cli/jobs): one unit per fold (and per
baseline fold), each an ordinary run folder ``OUT/fold-<k>/`` (``OUT/baseline/fold-<k>/``) as
``models/cv.py`` lays it out; the unit that finishes the last fold writes ``cv.json`` and ``cv.md``.

A unit's fingerprint covers the data (``Dataset.fingerprint``: classes, features, every trial's
frames, inputs and labels), the dataset and training configuration, the fold and the midas version.
A fold folder already holding a finished run of the same data and configuration (an earlier local
``--fold all``) is reused; one trained differently is moved aside (``fold-<k>.stale-<n>``) and
trained again.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, Callable, Sequence

from midas_cli import __version__
from midas_cli.errors import ConfigError
from midas_cli.jobs.rundir import Unit, fingerprint
from midas_cli.jobs.tasks import task_name
from midas_cli.models import cv
from midas_cli.models.data import DatasetConfig, build_dataset
from midas_cli.models.registry import LEGACY_TRAIN_CONFIG
from midas_cli.models.splits import GROUP_SPLITS, fold_groups
from midas_cli.session.outputs import out_folder

TASK = task_name(__name__)  # registered in jobs/tasks.py
log = logging.getLogger(__name__)


def plan_units(sessions: Sequence[Path], data_config: DatasetConfig, config: Any, out_dir: Path,
               baseline: str | None = cv.BASELINE) -> list[Unit]:
    """One unit per fold of ``config.split`` (then per baseline fold), as ``cv.run_cv`` would train them.
    ``config`` is a ``models.train.TrainConfig``."""
    if config.split not in GROUP_SPLITS:
        raise ConfigError(f"cross-validation needs a group split ({', '.join(GROUP_SPLITS)}), got {config.split!r}")
    dataset = build_dataset(sessions, data_config)
    groups = fold_groups(dataset, config.split)
    if len(groups) < 2:
        raise ConfigError(f"split {config.split} needs at least 2 groups, the data have {len(groups)}")
    out_dir = out_folder(out_dir)
    jobs = cv.cv_jobs(config, out_dir, baseline)
    data = dataset.fingerprint()
    units = []
    for job_config, root in jobs:
        for k in range(len(groups)):
            args = {"sessions": [str(Path(s).resolve()) for s in sessions], "data_config": data_config.to_json(),
                    "train_config": asdict(replace(job_config, fold=k)), "run_dir": str(cv.fold_dir(root, k)),
                    "cv_root": str(out_dir), "data_fingerprint": data}
            units.append(Unit(f"{job_config.model} fold {k} ({config.split} {groups[k]})", args,
                              fingerprint(TASK, args, __version__)))
    return units


def _same_run(run_dir: Path, args: dict[str, Any]) -> bool:
    """``run_dir`` holds a finished run of this data and training configuration."""
    from midas_cli.models.train import TrainConfig

    try:
        record = json.loads((run_dir / "run.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    wanted = asdict(TrainConfig(**args["train_config"]).resolved())
    recorded = {k: v for k, v in {**LEGACY_TRAIN_CONFIG, **record.get("train_config", {})}.items() if k != "device"}
    return ((run_dir / "metrics.json").is_file() and record.get("data_fingerprint") == args["data_fingerprint"]
            and recorded == {k: v for k, v in wanted.items() if k != "device"})


def run_unit(args: dict[str, Any], progress: Callable[[int, int, dict], None] | None = None) -> dict[str, Any]:
    """Train one fold (a unit's ``args``); its test summary, and cv.json / cv.md once every fold is there."""
    from midas_cli.models.train import TrainConfig, train_run

    run_dir = Path(args["run_dir"])
    if (run_dir / "run.json").exists() and not _same_run(run_dir, args):
        n = 0
        while run_dir.with_name(f"{run_dir.name}.stale-{n}").exists():
            n += 1
        aside = run_dir.with_name(f"{run_dir.name}.stale-{n}")
        log.warning("%s was trained on other data or settings: moved to %s, training again", run_dir, aside.name)
        run_dir.rename(aside)
    if not (run_dir / "metrics.json").is_file():
        train_run([Path(s) for s in args["sessions"]], DatasetConfig.from_json(args["data_config"]),
                  TrainConfig(**args["train_config"]), run_dir, progress)
    summary = json.loads((run_dir / "metrics.json").read_text(encoding="utf-8"))["test"]["summary"]
    root = Path(args["cv_root"])
    if cv.complete(root):
        cv.summarise(root)  # every fold unit that finds the set complete writes the same files, atomically
    return {"result": {"run": str(run_dir), "test": summary}, "outputs": [str(run_dir / "metrics.json")]}
