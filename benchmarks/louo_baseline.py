"""A weak reference for gesture recognition: per-frame multinomial logistic regression, LOUO.

Same inputs as `midas train gestures` (models.data.build_dataset: modalities, feature sets, the platform's
model rate; frames labelled -1 are left out), normalised over the training frames; every frame is
classified on its own (no temporal context). For each held-out subject (the LOUO folds of
models.splits: the test subject; training = every other subject, the validation subject included) it
reports the accuracy over the held-out subject's labelled frames. On a simulated dataset this shows
how much the simulator's difficulty leaves to temporal models (issue 19 item 3).

    PYTHONPATH=. .venv/bin/python benchmarks/louo_baseline.py SESSIONS_DIR [--modalities emht]
        [--features pos,ori,vel] [--folds 0,1] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def logistic_regression(x: np.ndarray, y: np.ndarray, classes: int, steps: int = 300, seed: int = 0):  # noqa: ANN201
    """A fitted linear classifier (torch.nn.Linear), full-batch Adam with a little L2, balanced classes."""
    import torch

    torch.manual_seed(seed)
    model = torch.nn.Linear(x.shape[1], classes)
    xt, yt = torch.from_numpy(x), torch.from_numpy(y)
    counts = np.bincount(y, minlength=classes).astype(np.float32)
    weight = torch.from_numpy(np.where(counts > 0, counts.sum() / np.maximum(counts, 1) / classes, 0.0).astype(np.float32))
    optimiser = torch.optim.Adam(model.parameters(), lr=0.05, weight_decay=1e-4)
    for _ in range(steps):
        optimiser.zero_grad()
        torch.nn.functional.cross_entropy(model(xt), yt, weight=weight).backward()
        optimiser.step()
    return model


def run(sessions: list[Path], modalities: tuple[str, ...], features: tuple[str, ...], folds: list[int] | None) -> dict:
    import torch

    from midas_cli.models.data import DatasetConfig, Normaliser, build_dataset

    torch.set_num_threads(1)
    dataset = build_dataset(sessions, DatasetConfig(modalities, features))
    order = list(dataset.config.modalities)
    subjects = sorted({t.subject for t in dataset.trials})
    results = []
    for fold in folds if folds is not None else range(len(subjects)):
        test = subjects[fold]
        train = [t for t in dataset.trials if t.subject != test]
        held = [t for t in dataset.trials if t.subject == test]
        normaliser = Normaliser.fit([t.stacked(order) for t in train])
        x = np.concatenate([normaliser.apply(t.stacked(order)) for t in train]).astype(np.float32)
        y = np.concatenate([t.labels for t in train])
        model = logistic_regression(x[y >= 0], y[y >= 0], len(dataset.classes))
        xt = np.concatenate([normaliser.apply(t.stacked(order)) for t in held]).astype(np.float32)
        yt = np.concatenate([t.labels for t in held])
        with torch.no_grad():
            predicted = model(torch.from_numpy(xt)).argmax(1).numpy()
        kept = yt >= 0
        results.append({"fold": fold, "test_subject": test, "frames": int(kept.sum()),
                        "accuracy": round(float((predicted[kept] == yt[kept]).mean()), 4)})
    return {"model": "per-frame logistic regression", "modalities": list(modalities), "features": list(features),
            "classes": list(dataset.classes), "folds": results,
            "mean_accuracy": round(float(np.mean([r["accuracy"] for r in results])), 4)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sessions", nargs="+", type=Path)
    parser.add_argument("--modalities", default="emht")
    parser.add_argument("--features", default="pos,ori,vel")
    parser.add_argument("--folds", default=None, help="comma list of fold indices (default: all)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    from midas_cli.session.reader import find_sessions

    sessions = [s for p in args.sessions for s in find_sessions(p)]
    folds = [int(f) for f in args.folds.split(",")] if args.folds else None
    result = run(sessions, tuple(args.modalities.split(",")), tuple(args.features.split(",")), folds)
    if args.json:
        print(json.dumps(result, indent=2))
        return
    for r in result["folds"]:
        print(f"fold {r['fold']} (subject {r['test_subject']}): accuracy {r['accuracy']:.3f} over {r['frames']} frames")
    print(f"mean accuracy {result['mean_accuracy']:.3f}", file=sys.stdout)


if __name__ == "__main__":
    main()
