"""Kinematic feature sets of the gesture models: columns of a session's aligned table -> arrays.

Feature sets per modality (columns of the aligned table; velocities are time derivatives of the
positions on the frame clock, in mm/s, computed before resampling; angular velocities (rad/s, base
frame) are central differences of the orientations, ``geometry.angular_velocities``):

========  ===================================  =====================  ===================  ===========  ============
modality  pos                                  ori                    vel                  angvel       grasper
========  ===================================  =====================  ===================  ===========  ============
emht      ``emht.s{1-4}_{x,y,z}_mm`` (12)       sin, cos of the 12     d/dt of pos (12)     per sensor   thumb-middle
                                               sensor angles (24)                          (12)         distance (2)
handkp    ``handkp.{hand}_{kp}_{x,y,z}_mm`` (12)  --                   d/dt of pos (12)     --           as emht (2)
mtm, psm  ``{side}_{x,y,z}_mm`` (6)             rotation matrix (18)   logged ``_v*_mm_s``  per arm (6)  ``_grasper_deg``
                                               or quaternion (8)      (6)                               (2)
image     all ``features`` columns of the NPZ; feature sets do not apply
========  ===================================  =====================  ===================  ===========  ============

Counts are for both sides; ``sides`` (``left``/``right``) keeps one arm, hand or the EmHT sensors on
that hand (``HANDS``) and halves them. Robot orientation (``rotation``): ``matrix`` by default -- the 9
entries are continuous in the motion and unique, as in the JIGSAWS kinematics, whereas a quaternion
has two signs per rotation and the stored w >= 0 convention flips it whenever w crosses 0;
``quat`` keeps the logged quaternion (what runs before this option used).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from midas_cli.errors import SessionError
from midas_cli.geometry import angular_velocities, matrices_from_angles, matrices_from_quaternions
from midas_cli.session.derived import AlignedTable

HANDS = {"left": (2, 1), "right": (3, 4)}  # EmHT (thumb, middle) sensor numbers
SIDES = ("left", "right")


def feature_block(table: AlignedTable, times_s: np.ndarray, modality: str, feature: str, path: Path,
                  sides: Sequence[str] = SIDES, rotation: str = "matrix") -> tuple[np.ndarray, list[str]] | None:
    """One feature set of one kinematic modality at the full frame rate ((N, D) float64, NaN = missing,
    and the D names), or None where the modality does not have it."""
    if feature == "clutch":
        return clutch(table, path)[:, None], ["clutch"]
    positions = _position_columns(modality, sides)
    if feature == "pos":
        return _columns(table, positions, path), positions
    if feature == "vel":
        if modality in ("mtm", "psm"):
            names = [f"{modality}.{s}_v{a}_mm_s" for s in sides for a in "xyz"]
            return _columns(table, names, path), names
        return _derivative(_columns(table, positions, path), times_s), [f"d/dt {n}" for n in positions]
    if feature in ("ori", "angvel"):
        rotations = _rotations(table, modality, path, sides)
        if rotations is None:
            return None
        if feature == "angvel":
            blocks = [angular_velocities(r, times_s) for r in rotations.values()]
            return np.concatenate(blocks, axis=1), [f"{n}_w{a}_rad_s" for n in rotations for a in "xyz"]
        return _orientation(table, modality, path, sides, rotation, rotations)
    return _grasper(table, modality, path, sides)


def is_position(name: str) -> bool:
    """Whether feature ``name`` is a position coordinate (the ``pos`` set of any modality; not its
    derivative)."""
    return not name.startswith("d/dt ") and name.endswith(("_x_mm", "_y_mm", "_z_mm"))


def is_orientation(name: str) -> bool:
    """Whether feature ``name`` is an orientation value (the ``ori`` set: a robot arm's rotation-matrix
    entry or quaternion component, an EmHT angle's sine or cosine)."""
    if name.startswith(("sin emht.", "cos emht.")):
        return True
    tail = name.rsplit("_", 1)[-1]
    return (len(tail) == 3 and tail[0] == "R" and tail[1:].isdigit()) or tail in ("qx", "qy", "qz", "qw")


def _emht_sensors(sides: Sequence[str]) -> list[int]:
    """EmHT sensor numbers worn on ``sides`` (HANDS), ascending."""
    return sorted(n for side in sides for n in HANDS[side])


def _position_columns(modality: str, sides: Sequence[str] = SIDES) -> list[str]:
    if modality == "emht":
        return [f"emht.s{s}_{a}_mm" for s in _emht_sensors(sides) for a in "xyz"]
    if modality == "handkp":
        return [f"handkp.{h}_{kp}_{a}_mm" for h in sides for kp in ("thumb", "middle") for a in "xyz"]
    return [f"{modality}.{s}_{a}_mm" for s in sides for a in "xyz"]


def _emht_angles(sensor: int) -> list[str]:
    return [f"emht.s{sensor}_{a}_deg" for a in ("azimuth", "elevation", "roll")]


def _rotations(table: AlignedTable, modality: str, path: Path,
               sides: Sequence[str]) -> dict[str, np.ndarray] | None:
    """Orientation per sensor / arm as (N, 3, 3) matrices (NaN where missing), keyed by a name
    prefix; None for HandKP (keypoints carry no orientation)."""
    if modality == "handkp":
        return None
    if modality == "emht":
        return {f"emht.s{n}": matrices_from_angles(_columns(table, _emht_angles(n), path))
                for n in _emht_sensors(sides)}
    return {f"{modality}.{s}": matrices_from_quaternions(_columns(table, [f"{modality}.{s}_q{a}" for a in "xyzw"], path))
            for s in sides}


def _orientation(table: AlignedTable, modality: str, path: Path, sides: Sequence[str], rotation: str,
                 rotations: dict[str, np.ndarray]) -> tuple[np.ndarray, list[str]]:
    """EmHT: sin and cos of the sensor angles. Robot arms: the rotation matrix (9, row-major, the
    JIGSAWS layout) or the logged quaternion (4, xyzw), per ``rotation``."""
    if modality == "emht":
        names = [n for s in _emht_sensors(sides) for n in _emht_angles(s)]
        radians = np.radians(_columns(table, names, path))
        return (np.concatenate([np.sin(radians), np.cos(radians)], axis=1),
                [f"sin {n}" for n in names] + [f"cos {n}" for n in names])
    if rotation == "matrix":
        blocks = [r.reshape(len(r), 9) for r in rotations.values()]  # (N, 3, 3) -> (N, 9)
        return np.concatenate(blocks, axis=1), [f"{n}_R{i}{j}" for n in rotations for i in range(3) for j in range(3)]
    names = [f"{modality}.{s}_q{a}" for s in sides for a in "xyzw"]
    return _columns(table, names, path), names


def _grasper(table: AlignedTable, modality: str, path: Path, sides: Sequence[str]) -> tuple[np.ndarray, list[str]]:
    if modality in ("mtm", "psm"):
        names = [f"{modality}.{s}_grasper_deg" for s in sides]
        return _columns(table, names, path), names
    distance = []
    for side in sides:
        if modality == "emht":
            thumb, middle = (_position_columns_of_sensor(n) for n in HANDS[side])
        else:
            thumb, middle = ([f"handkp.{side}_{kp}_{a}_mm" for a in "xyz"] for kp in ("thumb", "middle"))
        distance.append(np.linalg.norm(_columns(table, thumb, path) - _columns(table, middle, path), axis=1))
    return np.column_stack(distance), [f"{modality}.{h}_grasper_mm" for h in sides]


def _position_columns_of_sensor(sensor: int) -> list[str]:
    return [f"emht.s{sensor}_{a}_mm" for a in "xyz"]


def _columns(table: AlignedTable, names: list[str], path: Path) -> np.ndarray:
    missing = [n for n in names if not table.has(n)]
    if missing:
        raise SessionError(f"{path}: the aligned table lacks {', '.join(missing[:4])}"
                           f"{' ...' if len(missing) > 4 else ''}: is that stream recorded? (run `midas align`)")
    return np.column_stack([table.column(n) for n in names])


def _derivative(values: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """d/dt per column (N, D) in units per second; NaN where a neighbour is missing."""
    if len(times_s) < 2:
        return np.zeros_like(values)
    return np.gradient(values, times_s, axis=0)


def clutch(table: AlignedTable, path: Path) -> np.ndarray:
    """(N,) clutch state 0/1 (NaN -> 0) from the aligned ``clutch`` column (or its sources)."""
    for name in ("clutch", "mtm.clutch", "fps.ch5_pressed"):
        if table.has(name):
            return np.nan_to_num(table.column(name), nan=0.0)
    raise SessionError(f"{path}: no clutch signal in the aligned table (needs an fps or mtm stream); "
                       "drop --exclude-clutch or the clutch feature set")
