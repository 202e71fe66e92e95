"""Stream layout of robot kinematics as a surgical robot logs them (MTM and PSM, both arms).

Shared by `midas simulate dataset` (writes the streams) and the analysis commands (read them), so the
column names cannot drift. Positions in mm in the robot's own frame (``mtm`` or ``psm``), orientation
as a unit quaternion with the scalar last, velocities in mm/s, grasper opening angle in degrees.
"""

from __future__ import annotations

from midas_cli.errors import ConfigError
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec

KINEMATICS_STREAMS = ("mtm", "psm")
SIDES = ("left", "right")
NOMINAL_RATE_HZ = 100.0


def side_columns(side: str) -> list[str]:
    """Column names of one arm, in file order (position, quaternion, velocity, grasper)."""
    return ([f"{side}_{a}_mm" for a in "xyz"] + [f"{side}_q{a}" for a in "xyzw"]
            + [f"{side}_v{a}_mm_s" for a in "xyz"] + [f"{side}_grasper_deg"])


def kinematics_spec(name: str, rate_hz: float = NOMINAL_RATE_HZ) -> StreamSpec:
    """The StreamSpec of stream ``name`` ("mtm" or "psm"): seq, t_host_ns, t_device_s, 11 columns per arm
    (left then right), then ``clutch`` (0/1, the clutch pedal as the robot saw it)."""
    if name not in KINEMATICS_STREAMS:
        raise ConfigError(f"kinematics stream {name!r} unknown (expected one of {', '.join(KINEMATICS_STREAMS)})")
    columns = [SEQ, T_HOST, Column("t_device_s", "float", "s", 6, clock="device", description="robot clock")]
    for side in SIDES:
        columns += [Column(f"{side}_{a}_mm", "float", "mm", 3, frame=name, description=f"{side} arm position")
                    for a in "xyz"]
        columns += [Column(f"{side}_q{a}", "float", "", 6, frame=name, description=f"{side} orientation quaternion")
                    for a in "xyzw"]
        columns += [Column(f"{side}_v{a}_mm_s", "float", "mm/s", 3, frame=name, description=f"{side} velocity")
                    for a in "xyz"]
        columns.append(Column(f"{side}_grasper_deg", "float", "deg", 3, description=f"{side} grasper opening angle"))
    columns.append(Column("clutch", "int", "bool", description="1 while the clutch pedal is pressed"))
    return StreamSpec(name, "robot", tuple(columns), rate_hz, f"{name.upper()} kinematics as logged by the robot")
