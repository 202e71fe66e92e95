"""`midas train ablation` as units of a batch run (midas_cli/jobs): one unit per (model, grid row) cell,
a training run (or, with ``--fold all``, a whole cross-validation) in ``OUT/runs/<model>__<row>/``.
The submitting command writes the table from the cells' results once every unit has finished.

A unit's fingerprint covers the sessions (each one's ``derived/aligned.json``, which names its
alignment run, and its ``labels/`` files), the cell, the training configuration and the midas version.
A cell's run folder trained with another configuration or on other data is moved aside
(``<name>.stale-<n>``) and trained again; one with the same configuration and data is reused (as an
interrupted ablation always did).
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, Callable, Sequence

from midas_cli import __version__
from midas_cli.errors import MidasError
from midas_cli.jobs.rundir import Unit, file_digest, fingerprint
from midas_cli.jobs.tasks import task_name
from midas_cli.models.ablation import GridRow, run_cell
from midas_cli.models.data import DatasetConfig, build_dataset
from midas_cli.models.registry import LEGACY_TRAIN_CONFIG, MODELS
from midas_cli.models.train import TrainConfig

TASK = task_name(__name__)  # registered in jobs/tasks.py
log = logging.getLogger(__name__)


def sessions_digest(sessions: Sequence[Path]) -> list[Any]:
    """What training reads of each session, summarised: its aligned table's metadata and its labels."""
    digest = []
    for session in sessions:
        labels = sorted((Path(session) / "labels").rglob("*")) if (Path(session) / "labels").is_dir() else []
        digest.append([str(session), file_digest(Path(session) / "derived" / "aligned.json"),
                       [(p.name, file_digest(p)) for p in labels if p.is_file()]])
    return digest


def plan_units(sessions: Sequence[Path], rows: Sequence[GridRow], models: Sequence[str], base: TrainConfig,
               out_dir: Path, cv: bool) -> list[Unit]:
    data = sessions_digest(sessions)
    units = []
    for model in models:
        for row in rows:
            args = {"sessions": [str(Path(s).resolve()) for s in sessions], "model": model,
                    "row": [list(row.modalities), list(row.features), row.exclude_clutch],
                    "train_config": asdict(base), "out_dir": str(Path(out_dir).resolve()), "cv": cv}
            units.append(Unit(f"{MODELS[model].title} {row.slug()}", args, fingerprint(TASK, args, data, __version__)))
    return units


def _trained_otherwise(run_dir: Path, config: TrainConfig, cv: bool, sessions: Sequence[Path], row: GridRow) -> bool:
    """``run_dir`` (or, cross-validated, any of its folds) records another training configuration or other
    data (``Dataset.fingerprint``: the sessions' frames, inputs and labels) than this cell would train on."""
    records = sorted(run_dir.glob("fold-*/run.json")) if cv else [run_dir / "run.json"]
    try:
        recorded = [json.loads(p.read_text(encoding="utf-8")) for p in records if p.is_file()]
    except (OSError, ValueError):
        return True
    if not recorded:
        return False
    ignore = ("device", "fold")
    wanted = {k: v for k, v in asdict(config.resolved()).items() if k not in ignore}
    if any({k: v for k, v in {**LEGACY_TRAIN_CONFIG, **r.get("train_config", {})}.items() if k not in ignore} != wanted
           for r in recorded):
        return True
    try:
        data = build_dataset(sessions, DatasetConfig(row.modalities, row.features, exclude_clutch=row.exclude_clutch))
    except MidasError:
        return False  # the cell will be skipped with this error anyway
    return any(r.get("data_fingerprint") != data.fingerprint() for r in recorded)


def run_unit(args: dict[str, Any], progress: Callable[[int, int, dict], None] | None = None) -> dict[str, Any]:
    """Train one cell (a unit's ``args``); its table row or its skip reason."""
    row = GridRow(tuple(args["row"][0]), tuple(args["row"][1]), bool(args["row"][2]))
    base = TrainConfig(**args["train_config"])
    out_dir = Path(args["out_dir"])
    run_dir = out_dir / "runs" / f"{args['model']}__{row.slug()}"
    sessions = [Path(p) for p in args["sessions"]]
    if run_dir.exists() and _trained_otherwise(run_dir, replace(base, model=args["model"]), args["cv"], sessions, row):
        n = 0
        while run_dir.with_name(f"{run_dir.name}.stale-{n}").exists():
            n += 1
        log.warning("%s was trained with other settings: moved to %s.stale-%d, training again", run_dir, run_dir.name, n)
        run_dir.rename(run_dir.with_name(f"{run_dir.name}.stale-{n}"))
    cell = run_cell(sessions, args["model"], row, base, out_dir, progress, args["cv"])
    return {"result": cell, "outputs": [] if "skipped" in cell else [str(run_dir)]}
