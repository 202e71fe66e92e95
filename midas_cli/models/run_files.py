"""A training run's folder: made for the run (and removed again if the run fails before writing in it),
then what a finished run writes there: ``run.json``, ``checkpoint.pt``, ``predictions/<trial>.csv``,
``plots/`` and, last, ``metrics.json`` (its presence says the run finished)."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import numpy as np
import torch

from midas_cli.errors import ConfigError
from midas_cli.models.data import GestureDataset
from midas_cli.models.plots import write_confusion_png, write_timeline_png
from midas_cli.session.outputs import out_child, out_folder, out_target, replacing, write_text

if TYPE_CHECKING:
    from midas_cli.models.sequences import Sequences


def write_run(out_dir: Path, run: dict, result: dict, model: torch.nn.Module, dataset: GestureDataset,
               test: Sequences, device: torch.device, save_checkpoint: bool = True) -> None:
    """Everything a finished run writes, ``metrics.json`` last (``result``'s predictions are taken out of it)."""
    preds = result["test"].pop("predictions")
    if "val" in result:
        result["val"].pop("predictions")
    write_text(out_target(out_dir / "run.json"), json.dumps(run, indent=2) + "\n")
    if save_checkpoint:
        state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
        with replacing(out_target(out_dir / "checkpoint.pt")) as tmp:
            torch.save({**run, "state_dict": state}, tmp)
    write_predictions(out_dir, dataset, test, preds)
    write_confusion_png(out_dir / "plots" / "confusion.png", np.asarray(result["test"]["confusion"]), dataset.classes)
    # last: metrics.json says the run is finished (cross-validation pools every fold's predictions once
    # each fold has it, from whichever fold ends last; folds run at once on a cluster)
    write_text(out_target(out_dir / "metrics.json"), json.dumps(result, indent=2) + "\n")


def write_predictions(out_dir: Path, dataset: GestureDataset, test: Sequences, preds: list[np.ndarray]) -> None:
    """predictions/<trial>.csv and plots/<trial>.png: test frames of each trial on its own timeline."""
    per_trial: dict[str, np.ndarray] = {}
    for (name, start, stop), pred in zip(test.units, preds):
        trial = dataset.trials[dataset.trial_index(name)]
        timeline = per_trial.setdefault(name, np.full(len(trial.labels), -1, dtype=np.int64))
        timeline[start:stop] = pred
    for name, timeline in sorted(per_trial.items()):
        trial = dataset.trials[dataset.trial_index(name)]
        tested = timeline >= 0
        rows = ["frame,truth,prediction"] + [
            f"{f},{dataset.classes[t] if t >= 0 else ''},{dataset.classes[p]}"
            for f, t, p in zip(trial.frames[tested], trial.labels[tested], timeline[tested])]
        write_text(out_child(out_dir / "predictions", f"{name}.csv"), "\n".join(rows) + "\n")
        write_timeline_png(out_child(out_dir / "plots", f"{name}.png"), trial.labels, timeline, dataset.classes, name)


@contextlib.contextmanager
def run_folder(out_dir: Path) -> Iterator[Path]:
    """``new_run_dir(out_dir)`` for the block; a folder it created is removed again if the block fails
    before writing anything into it (data refused, Ctrl-C while training): no empty run folder is left."""
    created = not Path(out_dir).expanduser().exists()
    folder = new_run_dir(out_dir)
    try:
        yield folder
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                folder.rmdir()  # only an empty folder: anything written stays
        raise


def new_run_dir(out_dir: Path) -> Path:
    out_dir = Path(out_dir)
    if (out_dir / "run.json").exists():
        raise ConfigError(f"{out_dir} already holds a run (run.json): choose a new --out folder")
    return out_folder(out_dir)
