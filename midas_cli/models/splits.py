"""Train/validation/test splits, seeded and stored with every run as plain JSON.

A split is three lists of *units* ``(trial name, start, stop)`` (frame rows of the trial's arrays,
stop exclusive); each unit is one sequence the network sees on its own.

* ``gesture`` -- the paper's protocol (Materials and Methods, "gesture-level train/validation/test
  split"): every trial is cut into gesture instances (maximal runs of one label; unlabelled frames
  end an instance), the instances of each class are shuffled and dealt 60/20/20 into
  train/validation/test, so every class keeps its share in every set. Performance is measured on
  held-out gesture *instances*, each a sequence of its own; trials are shared between sets (the paper
  says so: "rather than held-out trials").
* ``loto`` -- leave one trial out: fold k tests on trial k (in name order), validates on the next.
* ``louo`` -- leave one user out: fold k tests on every trial of subject k (sorted), validates on the
  next subject's trials.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from midas_cli.errors import ConfigError
from midas_cli.models.data import GestureDataset

SPLITS = ("gesture", "loto", "louo")
FRACTIONS = (0.6, 0.2, 0.2)
PARTS = ("train", "val", "test")


@dataclass
class Split:
    kind: str
    seed: int
    fold: int
    units: dict[str, list[tuple[str, int, int]]]  # part -> [(trial name, start, stop)]

    def to_json(self) -> dict:
        return {"kind": self.kind, "seed": self.seed, "fold": self.fold,
                **{part: [list(u) for u in self.units[part]] for part in PARTS}}

    @classmethod
    def from_json(cls, data: dict) -> "Split":
        return cls(data["kind"], int(data["seed"]), int(data["fold"]),
                   {part: [(str(n), int(a), int(b)) for n, a, b in data[part]] for part in PARTS})


def instances(labels: np.ndarray) -> list[tuple[int, int, int]]:
    """Gesture instances of one trial: (class, start, stop) for each maximal run of a label >= 0."""
    change = np.flatnonzero(labels[1:] != labels[:-1]) + 1
    starts = np.r_[0, change]
    stops = np.r_[change, len(labels)]
    return [(int(labels[a]), int(a), int(b)) for a, b in zip(starts, stops) if labels[a] >= 0]


def make_split(dataset: GestureDataset, kind: str, seed: int, fold: int = 0) -> Split:
    if kind == "gesture":
        return _gesture_split(dataset, seed)
    if kind in ("loto", "louo"):
        return _group_split(dataset, kind, seed, fold)
    raise ConfigError(f"split {kind!r} is unknown (expected one of {', '.join(SPLITS)})")


def _gesture_split(dataset: GestureDataset, seed: int) -> Split:
    rng = np.random.default_rng(seed)
    by_class: dict[int, list[tuple[str, int, int]]] = {}
    for trial in dataset.trials:
        for cls, start, stop in instances(trial.labels):
            by_class.setdefault(cls, []).append((trial.name, start, stop))
    units: dict[str, list] = {part: [] for part in PARTS}
    for cls in sorted(by_class):
        pool = by_class[cls]
        order = rng.permutation(len(pool))
        n_train, n_val = _shares(len(pool))
        units["train"] += [pool[i] for i in order[:n_train]]
        units["val"] += [pool[i] for i in order[n_train:n_train + n_val]]
        units["test"] += [pool[i] for i in order[n_train + n_val:]]
    return Split("gesture", seed, 0, {part: sorted(units[part]) for part in PARTS})


def _shares(n: int) -> tuple[int, int]:
    """(train, val) counts of n instances at 60/20/20; test gets the rest. With 3 or more instances
    every set gets at least one; with fewer, training comes first, then test."""
    if n < 3:
        return (n, 0) if n < 2 else (1, 0)
    n_val = max(1, int(round(n * FRACTIONS[1])))
    n_test = max(1, int(round(n * FRACTIONS[2])))
    return n - n_val - n_test, n_val


def _group_split(dataset: GestureDataset, kind: str, seed: int, fold: int) -> Split:
    key = (lambda t: t.name) if kind == "loto" else (lambda t: t.subject)
    groups = sorted({key(t) for t in dataset.trials})
    if len(groups) < 2:
        raise ConfigError(f"split {kind} needs at least 2 {'trials' if kind == 'loto' else 'subjects'}, "
                          f"the data have {len(groups)}")
    if not 0 <= fold < len(groups):
        raise ConfigError(f"--fold {fold} is out of range for {kind}: 0..{len(groups) - 1} ({len(groups)} groups)")
    test = groups[fold]
    val = groups[(fold + 1) % len(groups)] if len(groups) >= 3 else None
    whole = {t.name: (t.name, 0, len(t.labels)) for t in dataset.trials}
    part_of = {g: "test" if g == test else "val" if g == val else "train" for g in groups}
    units: dict[str, list] = {part: [] for part in PARTS}
    for trial in sorted(dataset.trials, key=lambda t: t.name):
        units[part_of[key(trial)]].append(whole[trial.name])
    return Split(kind, seed, fold, units)


def n_folds(dataset: GestureDataset, kind: str) -> int:
    """How many folds ``kind`` has on ``dataset`` (1 for the gesture split)."""
    if kind == "gesture":
        return 1
    key = (lambda t: t.name) if kind == "loto" else (lambda t: t.subject)
    return len({key(t) for t in dataset.trials})
