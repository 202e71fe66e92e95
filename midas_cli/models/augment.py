"""Training-time augmentation of the gesture models' input: shifts of position (and orientation) columns
(``--augment-shift SD``, ``--augment-features pos[,ori]``).

Why: on real kinematics the positions carry offsets per user and per setup (JIGSAWS Needle Passing,
training-split z-score units: user B's right patient-side arm sits 1.6 sd off in x and 2.3 in y; the
master arms' positions fall into two groups of users 2-3 sd apart, from where each surgeon clutched).
A model trained on the other users learns their positions and misreads a user who sits elsewhere. Each
training sequence, each epoch, gets every position column moved by its own constant, drawn from
N(0, (SD x the column's sd over the training split)^2): the shape of the motion is kept, where it happens
is blurred. With ``ori`` the orientation values (rotation-matrix entries, quaternion components, EmHT
angles' sines and cosines) are shifted the same way, one constant each: how a surgeon holds the master
controls differs more between users than where (Needle Passing user B's left master R11 sits 5.8 sd
off); a constant added to a matrix entry is not a rotation, it only blurs the absolute value, as for
the positions. Velocities and grasper angles are left as they are. Nothing changes at test time, so it
suits causal (live) models as well (unlike ``--normalise trial``, which uses a whole trial).

The draws come from their own generator (``default_rng([seed, STREAM])``), so a run with SD 0 draws
nothing and trains exactly as before; with SD > 0 the batch order and the weights' initialisation are
still those of the seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from midas_cli.errors import ConfigError
from midas_cli.models.features import is_orientation, is_position

STREAM = 0x5A1F  # the augmentation generator's stream, beside the batch-order generator of the same seed
SHIFTABLE = {"pos": is_position, "ori": is_orientation}  # --augment-features: which columns a shift moves


def check_sets(text: str) -> tuple[str, ...]:
    """``--augment-features`` (comma list of pos, ori) as a tuple; ConfigError for anything else."""
    sets = tuple(part.strip() for part in text.split(","))
    if not sets or any(s not in SHIFTABLE for s in sets) or len(set(sets)) != len(sets):
        raise ConfigError(f"--augment-features must be pos, ori or pos,ori, got {text!r}")
    return sets


@dataclass
class ColumnShift:
    """Adds a constant per (sequence, shifted column) to the training inputs, new draws every call."""

    columns: np.ndarray  # (P,) indices of the shifted columns in the stacked features
    scale: np.ndarray  # (P,) standard deviation of each column's shift
    rng: np.random.Generator

    def __call__(self, xs: list[np.ndarray]) -> list[np.ndarray]:
        """New (T_i, D) arrays: each ``xs[i]`` with its shifted columns moved (inputs unchanged)."""
        out = []
        for x in xs:
            shifted = x.copy()
            shifted[:, self.columns] += (self.rng.standard_normal(len(self.columns)) * self.scale).astype(x.dtype)
            out.append(shifted)
        return out


def input_shift(sd: float, sets: str, names: list[str], train: list[np.ndarray], seed: int) -> ColumnShift | None:
    """The shift of ``--augment-shift sd --augment-features sets`` for features ``names`` (stacked order),
    scaled on the training inputs ``train`` (as the model sees them, normalised); None for sd 0 or no
    such column."""
    tests = [SHIFTABLE[s] for s in check_sets(sets)]
    columns = np.array([i for i, name in enumerate(names) if any(t(name) for t in tests)], dtype=np.int64)
    if not sd or not columns.size or not train:
        return None
    spread = np.concatenate([x[:, columns] for x in train], axis=0).std(axis=0)
    return ColumnShift(columns, sd * spread, np.random.default_rng([seed, STREAM]))
