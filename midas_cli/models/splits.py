"""Train/validation/test splits, seeded and stored with every run as plain JSON.

A split is three lists of *units* ``(trial name, start, stop)`` (frame rows of the trial's arrays,
stop exclusive); each unit is one sequence the network sees on its own.

* ``gesture`` -- the paper's protocol (Materials and Methods, "gesture-level train/validation/test
  split"): every trial is cut into gesture instances (maximal runs of one label; unlabelled frames
  end an instance), the instances of each class are shuffled and dealt 60/20/20 into
  train/validation/test, so every class keeps its share in every set. Performance is measured on
  held-out gesture *instances*, each a sequence of its own; trials are shared between sets (the paper
  says so: "rather than held-out trials").
* ``loto`` -- leave one trial out: fold k tests on trial k (sessions in name order).
* ``louo`` -- leave one user out: fold k tests on every trial of subject k (subjects sorted; JIGSAWS:
  the 8 users B..I, as the dataset's authors define it); a user without sessions is simply no fold.
* ``loso`` -- leave one super-trial out (JIGSAWS): fold k tests on trial number k of EVERY user (the
  manifest's ``trial``; JIGSAWS ``Suturing_B001`` = trial 1, so T01..T05 give 5 folds).

Group splits (loto, louo, loso) train on every other group. Model selection never costs a group:
``validation="none"`` (the default, as in the papers) has no validation set -- the model of the last of
a fixed number of epochs is tested; ``validation="inner"`` takes a seeded ~15 % of the TRAINING trials
(at least one, only when two or more remain) as the validation set. The gesture split keeps its own
20 % of gesture instances for validation. The choice is saved with the split (``validation``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from midas_cli.errors import ConfigError
from midas_cli.models.data import GestureDataset

SPLITS = ("gesture", "loto", "louo", "loso")
GROUP_SPLITS = ("loto", "louo", "loso")
VALIDATIONS = ("none", "inner")
INNER_FRACTION = 0.15
FRACTIONS = (0.6, 0.2, 0.2)
PARTS = ("train", "val", "test")


@dataclass
class Split:
    kind: str
    seed: int
    fold: int
    units: dict[str, list[tuple[str, int, int]]]  # part -> [(trial name, start, stop)]
    validation: str = ""  # how the validation set was chosen, in words
    group: str | None = None  # group splits: the held-out trial / subject / super-trial
    groups: list[str] = field(default_factory=list)  # group splits: every group, fold k = groups[k]

    def to_json(self) -> dict:
        return {"kind": self.kind, "seed": self.seed, "fold": self.fold, "validation": self.validation,
                "group": self.group, "groups": list(self.groups),
                **{part: [list(u) for u in self.units[part]] for part in PARTS}}

    @classmethod
    def from_json(cls, data: dict) -> "Split":
        return cls(data["kind"], int(data["seed"]), int(data["fold"]),
                   {part: [(str(n), int(a), int(b)) for n, a, b in data[part]] for part in PARTS},
                   str(data.get("validation", "")), data.get("group"), list(data.get("groups", [])))


def instances(labels: np.ndarray) -> list[tuple[int, int, int]]:
    """Gesture instances of one trial: (class, start, stop) for each maximal run of a label >= 0."""
    change = np.flatnonzero(labels[1:] != labels[:-1]) + 1
    starts = np.r_[0, change]
    stops = np.r_[change, len(labels)]
    return [(int(labels[a]), int(a), int(b)) for a, b in zip(starts, stops) if labels[a] >= 0]


def make_split(dataset: GestureDataset, kind: str, seed: int, fold: int = 0, validation: str = "none") -> Split:
    if validation not in VALIDATIONS:
        raise ConfigError(f"--val {validation!r} is unknown (expected one of {', '.join(VALIDATIONS)})")
    if kind == "gesture":
        return _gesture_split(dataset, seed)
    if kind in GROUP_SPLITS:
        return _group_split(dataset, kind, seed, fold, validation)
    raise ConfigError(f"split {kind!r} is unknown (expected one of {', '.join(SPLITS)})")


def validation_text(kind: str, validation: str) -> str:
    """The validation choice in words (run.json, cv.json)."""
    if kind == "gesture":
        return "gesture instances (20 %, stratified); best-validation epoch"
    if validation == "inner":
        return (f"inner ({INNER_FRACTION:.0%} of the training trials, seeded, from the training groups only); "
                "best-validation epoch")
    return "none (fixed epochs)"


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
    return Split("gesture", seed, 0, {part: sorted(units[part]) for part in PARTS}, validation_text("gesture", "none"))


def _shares(n: int) -> tuple[int, int]:
    """(train, val) counts of n instances at 60/20/20; test gets the rest. With 3 or more instances
    every set gets at least one; with fewer, training comes first, then test."""
    if n < 3:
        return (n, 0) if n < 2 else (1, 0)
    n_val = max(1, int(round(n * FRACTIONS[1])))
    n_test = max(1, int(round(n * FRACTIONS[2])))
    return n - n_val - n_test, n_val


def _group_key(kind: str):
    if kind == "loto":
        return lambda t: t.name
    if kind == "louo":
        return lambda t: t.subject
    return lambda t: t.trial


GROUP_WORDS = {"loto": "trials", "louo": "subjects", "loso": "super-trials (trial numbers)"}


def fold_groups(dataset: GestureDataset, kind: str) -> list[str]:
    """The groups of a group split in fold order (fold k holds out ``groups[k]``); as strings."""
    key = _group_key(kind)
    return [str(g) for g in sorted({key(t) for t in dataset.trials})]


def _group_split(dataset: GestureDataset, kind: str, seed: int, fold: int, validation: str = "none") -> Split:
    key = _group_key(kind)
    groups = sorted({key(t) for t in dataset.trials})
    if len(groups) < 2:
        raise ConfigError(f"split {kind} needs at least 2 {GROUP_WORDS[kind]}, the data have {len(groups)}")
    if not 0 <= fold < len(groups):
        raise ConfigError(f"--fold {fold} is out of range for {kind}: 0..{len(groups) - 1} ({len(groups)} groups)")
    test = groups[fold]
    units: dict[str, list] = {part: [] for part in PARTS}
    for trial in sorted(dataset.trials, key=lambda t: t.name):
        units["test" if key(trial) == test else "train"].append((trial.name, 0, len(trial.labels)))
    if validation == "inner" and len(units["train"]) >= 2:
        n_val = max(1, int(round(len(units["train"]) * INNER_FRACTION)))
        pick = set(np.random.default_rng(seed).permutation(len(units["train"]))[:n_val].tolist())
        units["val"] = [u for i, u in enumerate(units["train"]) if i in pick]
        units["train"] = [u for i, u in enumerate(units["train"]) if i not in pick]
    return Split(kind, seed, fold, units, validation_text(kind, validation), str(test), [str(g) for g in groups])


def n_folds(dataset: GestureDataset, kind: str) -> int:
    """How many folds ``kind`` has on ``dataset`` (1 for the gesture split)."""
    if kind == "gesture":
        return 1
    return len(fold_groups(dataset, kind))
