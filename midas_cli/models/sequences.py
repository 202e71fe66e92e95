"""The units of a split as the models see them: normalised (T_i, D) arrays with their labels
(``Sequences``), the padded batches a training step takes, and an epoch's augmented training inputs.

Normalisation per ``DatasetConfig.normalise``: ``train`` with the training split's ``Normaliser``
(``fit_normaliser``), ``trial`` with each whole trial's own mean and std, ``none`` raw.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from midas_cli.models.augment import ColumnShift
from midas_cli.models.data import GestureDataset, Normaliser


@dataclass
class Sequences:
    """The units of one split part as arrays: ``x`` (T_i, D) float32 normalised, ``y`` (T_i,) int64."""

    units: list[tuple[str, int, int]]
    x: list[np.ndarray]
    y: list[np.ndarray]


def fit_normaliser(dataset: GestureDataset, train_units: list[tuple[str, int, int]],
                   order: list[str]) -> Normaliser | None:
    """The training-set normaliser for ``normalise == "train"``; None otherwise (per trial or none)."""
    if dataset.config.normalise != "train":
        return None
    return Normaliser.fit([dataset.trials[dataset.trial_index(n)].stacked(order)[a:b] for n, a, b in train_units])


def sequences(dataset: GestureDataset, units: list[tuple[str, int, int]], normaliser: Normaliser | None,
                order: list[str]) -> Sequences:
    """Units as arrays, normalised per ``dataset.config.normalise``: with the training-set
    ``normaliser``, with each whole trial's own mean and std ("trial"), or not at all ("none")."""
    xs, ys = [], []
    for name, start, stop in units:
        trial = dataset.trials[dataset.trial_index(name)]
        x = trial.stacked(order)
        if dataset.config.normalise == "trial":
            xs.append(Normaliser.fit([x]).apply(x[start:stop]))
        elif normaliser is None:
            xs.append(x[start:stop].astype(np.float32))
        else:
            xs.append(normaliser.apply(x[start:stop]))
        ys.append(trial.labels[start:stop])
    return Sequences(list(units), xs, ys)


def padded_batches(seqs: Sequences, order: np.ndarray, batch_size: int):
    """Padded batches: x (B, D, T_max) float32, y (B, T_max) long (-1 on padding), mask (B, T_max) bool."""
    for start in range(0, len(order), batch_size):
        pick = order[start:start + batch_size]
        t_max = max(len(seqs.y[i]) for i in pick)
        dim = seqs.x[pick[0]].shape[1]
        x = np.zeros((len(pick), dim, t_max), dtype=np.float32)
        y = np.full((len(pick), t_max), -1, dtype=np.int64)
        for row, i in enumerate(pick):
            t = len(seqs.y[i])
            x[row, :, :t] = seqs.x[i].T  # (T, D) -> (D, T)
            y[row, :t] = seqs.y[i]
        mask = np.zeros((len(pick), t_max), dtype=bool)
        for row, i in enumerate(pick):
            mask[row, :len(seqs.y[i])] = True
        yield torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(mask)


def epoch_inputs(train: Sequences, augment: ColumnShift | None) -> Sequences:
    """One epoch's training inputs: ``train`` as it is, or with ``augment``'s new draws."""
    return train if augment is None else replace(train, x=augment(train.x))
