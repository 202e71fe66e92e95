"""Re-score finished JIGSAWS cross-validation runs (gestures_jigsaws.py) with `--min-segment` settings,
from their raw predictions: how the offline clean-up changes accuracy, edit and F1@k on the development
tasks, without training again.

For each run folder (``fold-<k>/`` with run.json and predictions/), each fold's minimum segment comes
from that fold's own training split exactly as ``train gestures`` computes it (``models.postprocess``:
the dataset rebuilt with the run's dataset config, the training units' labels at the model rate); the
fold's test predictions are merged and scored with ``models.metrics``: pooled over all test videos (the
MS-TCN way) and averaged per video. The runs must hold raw predictions: trained before the option existed
or with ``--min-segment none``.

    .venv/bin/python benchmarks/rescore_jigsaws.py RUN_DIR:SESSIONS_DIR:TASK ... [--settings none,auto,1.0,2.0]
        # -> results/gestures_jigsaws_rescored.json and a table on stdout
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import RESULTS, machine_info  # noqa: E402
from report_gestures import rescored_table  # noqa: E402

from midas_cli.models import metrics as M  # noqa: E402
from midas_cli.models import postprocess  # noqa: E402
from midas_cli.models.data import DatasetConfig, build_dataset  # noqa: E402
from midas_cli.models.splits import Split  # noqa: E402

KEYS = ("accuracy", "edit", "f1@10", "f1@25", "f1@50")


def fold_data(fold: Path, cache: dict[str, Any]) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray], float,
                                                            list[str]]:
    """A fold's test predictions and truths (class indices, per trial), its training labels and rate."""
    run = json.loads((fold / "run.json").read_text(encoding="utf-8"))
    classes = list(run["classes"])
    key = json.dumps(run["dataset_config"], sort_keys=True)
    if key not in cache:
        cache[key] = build_dataset(cache["sessions"], DatasetConfig.from_json(run["dataset_config"]), classes=classes)
    dataset = cache[key]
    split = Split.from_json(run["split"])
    train = [dataset.trials[dataset.trial_index(name)].labels[a:b] for name, a, b in split.units["train"]]
    index = {c: i for i, c in enumerate(classes)}
    preds, truths = [], []
    for path in sorted((fold / "predictions").glob("*.csv")):
        table = pd.read_csv(path, dtype=str, keep_default_na=False)
        preds.append(np.array([index[c] for c in table["prediction"]]))
        truths.append(np.array([index.get(c, -1) if c else -1 for c in table["truth"]]))
    return preds, truths, train, dataset.trials[0].rate_hz, classes


def rescore(run_dir: Path, sessions: list[Path], settings: list[str]) -> list[dict[str, Any]]:
    """One row per setting: pooled and per-video figures over the run's finished folds."""
    cache: dict[str, Any] = {"sessions": sessions}
    folds = [fold_data(f, cache) for f in sorted(run_dir.glob("fold-*")) if (f / "metrics.json").is_file()]
    rows = []
    for setting in settings:
        preds, truths, minima = [], [], []
        for fold_preds, fold_truths, train, rate, _ in folds:
            minimum = postprocess.min_frames(setting, train, rate, causal=False)
            minima.append(minimum)
            preds += [postprocess.merge_short_segments(p, minimum) for p in fold_preds]
            truths += fold_truths
        classes = folds[0][4]
        pooled = M.evaluate(preds, truths, classes)["summary"]
        videos = [M.evaluate([p], [t], classes)["summary"] for p, t in zip(preds, truths)]
        rows.append({"run_dir": str(run_dir), "setting": setting, "folds": len(folds), "videos": len(preds),
                     "min_segment_frames": minima, "pooled": {k: pooled[k] for k in KEYS},
                     "per_video": {k: float(np.mean([v[k] for v in videos])) for k in KEYS}})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="RUN_DIR:SESSIONS_DIR:TASK (the sessions the run trained on)")
    parser.add_argument("--settings", default="none,auto,1.0,1.5,2.0")
    args = parser.parse_args()
    rows = []
    for spec in args.runs:
        run_dir, sessions_dir, task = spec.split(":")
        sessions = sorted(p for p in Path(sessions_dir).iterdir() if (p / "manifest.json").is_file())
        rows += [{"task": task, **row} for row in rescore(Path(run_dir), sessions, args.settings.split(","))]
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "gestures_jigsaws_rescored.json").write_text(
        json.dumps({"machine": machine_info(), "rows": rows}, indent=2) + "\n", encoding="utf-8")
    print("\n".join(rescored_table(rows)))


if __name__ == "__main__":
    main()
