"""Columns derived from the associated raw columns of an aligned table: EmHT hand points, grasper
distances and velocities, gap-filled HandKP hand points, robot orientations from quaternions, and the
clutch. Each ``add_*`` reads columns from, and adds columns to, a ``ColumnSet`` (or ``StagedColumns``)."""

from __future__ import annotations

import numpy as np

from midas_cli.analysis.calibration import TARGETS
from midas_cli.analysis.columns import ColumnSet
from midas_cli.analysis.sync import fill_gaps, velocity_mm_s
from midas_cli.geometry import angles_from_matrices, matrices_from_quaternions

HANDS = ("left", "right")
EMHT_SENSORS = {"left": (2, 1), "right": (3, 4)}  # (thumb, middle) trakSTAR sensor numbers
CLUTCH_FPS_CHANNEL = 5  # the paper's "Pedal 5 = Clutch"


def emht_sensor_arrays(columns: ColumnSet, prefix: str = "emht") -> tuple[np.ndarray, np.ndarray] | None:
    """(N, 4, 3) positions (mm) and (N, 4, 3) yaw/pitch/roll (deg) of sensors 1..4, or None."""
    names = [f"{prefix}.s{s}_{a}_mm" for s in range(1, 5) for a in "xyz"]
    if any(columns.get(n) is None for n in names):
        return None
    angles = [f"{prefix}.s{s}_{a}_deg" for s in range(1, 5) for a in ("azimuth", "elevation", "roll")]
    pos = columns.stack(names).reshape(-1, 4, 3)
    ang = columns.stack(angles).reshape(-1, 4, 3) if all(columns.get(n) is not None for n in angles) else None
    return pos, ang


def hand_points(sensor_pos: np.ndarray) -> dict[str, np.ndarray]:
    """Hand point (N, 3) = midpoint of the thumb and middle sensors, per hand."""
    return {h: (sensor_pos[:, t - 1] + sensor_pos[:, m - 1]) / 2 for h, (t, m) in EMHT_SENSORS.items()}


def add_emht_features(columns: ColumnSet, t_s: np.ndarray) -> None:
    """Hand points, grasper distances and hand velocities from the aligned EmHT sensors."""
    arrays = emht_sensor_arrays(columns)
    if arrays is None:
        return
    pos = arrays[0]
    for hand, point in hand_points(pos).items():
        thumb, middle = EMHT_SENSORS[hand]
        for k, axis in enumerate("xyz"):
            columns.add(f"emht.{hand}_hand_{axis}_mm", point[:, k], "mm", "emht", frame="emht_transmitter",
                        description="midpoint of the thumb and middle sensors")
        columns.add(f"emht.{hand}_grasper_mm", np.linalg.norm(pos[:, thumb - 1] - pos[:, middle - 1], axis=1), "mm",
                    "emht", description="thumb-middle sensor distance (grasper opening)")
        velocity = velocity_mm_s(point, t_s)
        for k, axis in enumerate("xyz"):
            columns.add(f"emht.{hand}_v{axis}_mm_s", velocity[:, k], "mm/s", "emht", frame="emht_transmitter",
                        description="hand point velocity (central differences on the frame clock)")


def add_handkp_features(columns: ColumnSet, t_s: np.ndarray, spline_max_gap_s: float) -> None:
    """Per hand: gap-filled keypoint midpoint in the camera frame and which frames were filled."""
    for hand in HANDS:
        names = [f"handkp.{hand}_{kp}_{a}_mm" for kp in ("thumb", "middle") for a in "xyz"]
        if any(columns.get(n) is None for n in names):
            continue
        keypoints = columns.stack(names)  # (N, 6): thumb xyz, middle xyz
        midpoint = (keypoints[:, :3] + keypoints[:, 3:]) / 2
        raw_valid = np.isfinite(midpoint).all(axis=1)
        filled, code = fill_gaps(t_s, midpoint, spline_max_gap_s)
        for k, axis in enumerate("xyz"):
            columns.add(f"handkp.{hand}_hand_{axis}_mm", filled[:, k], "mm", "handkp", frame="camera",
                        description="thumb-middle keypoint midpoint; gaps filled (see _filled)")
        columns.add(f"handkp.{hand}_filled", np.where(code < 0, np.nan, code), "code", "handkp",
                    description="0 detected, 1 cubic-spline filled (gap <= 1 s), 2 forward-filled")
        columns.add(f"handkp.{hand}_raw_valid", raw_valid.astype(float), "bool", "handkp",
                    description="1 where the hand was detected in the associated frame")


def add_clutch(columns: ColumnSet) -> None:
    """``clutch`` (0/1): robot clutch telemetry (mtm stream) where present, else the FPS clutch pedal."""
    for name, source in (("mtm.clutch", "mtm"), (f"fps.ch{CLUTCH_FPS_CHANNEL}_pressed", "fps")):
        values = columns.get(name)
        if values is not None:
            columns.add("clutch", values, "bool", source, description=f"clutch state from {name}")
            return


def add_robot_orientation(columns: ColumnSet) -> None:
    """``mtm.<hand>_{yaw,pitch,roll}_deg`` / ``psm...`` from the logged quaternions (for evaluation)."""
    for robot in TARGETS:
        for hand in HANDS:
            names = [f"{robot}.{hand}_q{a}" for a in "xyzw"]
            if any(columns.get(n) is None for n in names):
                continue
            angles = angles_from_matrices(matrices_from_quaternions(columns.stack(names)))
            for k, name in enumerate(("yaw", "pitch", "roll")):
                columns.add(f"{robot}.{hand}_{name}_deg", angles[:, k], "deg", robot, frame=robot,
                            description="from the logged quaternion (Rz @ Ry @ Rx convention)")
