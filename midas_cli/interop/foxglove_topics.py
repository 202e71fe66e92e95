"""How a midas stream looks in Foxglove: the topics, schemas and messages shared by the MCAP export and the
live WebSocket view (``midas record --foxglove``), built with the ``foxglove-sdk`` package.

* every stream is a JSON topic ``/<stream>`` whose JSON Schema gives each column ONE type (``integer``,
  ``number`` or ``string``: Foxglove Studio 1.x and Lichtblick reject a type list such as
  ``["number", "null"]``); a missing value is left out of the message (JSON has no NaN), so only
  ``seq`` and ``t_host_ns`` are required;
* the operator's markers (stream ``events``) are ``foxglove.Log`` messages on ``/events``;
* a stream with 6-DoF sensors (columns ``<p>_{x,y,z}_mm`` and either ``<p>_{azimuth,elevation,roll}_deg``,
  the EmHT layout, or a quaternion ``<p>_q{x,y,z,w}``, the robot arms' layout of ``mtm``/``psm``) also
  has ``/<stream>/transforms`` (``foxglove.FrameTransforms``: parent frame = the position columns'
  frame, e.g. ``emht_transmitter`` or ``psm``, child frame ``<stream>/<p>``; metres and unit
  quaternions), so the 3-D panel shows the sensors and the arms moving; a sensor with a missing value
  (or a zero quaternion) is left out of that row's message. (No ``PosesInFrame`` copy of the same
  poses: it doubled the file and the export time.)
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from midas_cli.geometry import quaternions_from_angles
from midas_cli.session.schema import StreamSpec

JSON_TYPES = {"int": "integer", "float": "number", "text": "string"}
REQUIRED = ("seq", "t_host_ns")


@dataclass(frozen=True)
class SensorColumns:
    """The columns of one 6-DoF sensor of a stream: position (mm) and orientation, either azimuth,
    elevation, roll (deg; 3 columns) or a quaternion x, y, z, w (4 columns)."""

    name: str
    position: tuple[str, str, str]
    orientation: tuple[str, ...]
    parent_frame: str


def _orientation(prefix: str, names: set[str]) -> tuple[str, ...] | None:
    """The orientation columns of sensor ``prefix``: its angles (EmHT) or its quaternion (robot arms)."""
    for columns in ((f"{prefix}_azimuth_deg", f"{prefix}_elevation_deg", f"{prefix}_roll_deg"),
                    tuple(f"{prefix}_q{a}" for a in "xyzw")):
        if names.issuperset(columns):
            return columns
    return None


def sensor_columns(spec: StreamSpec) -> list[SensorColumns]:
    """The stream's 6-DoF sensors, in column order (none for a stream with positions only)."""
    names = set(spec.column_names)
    sensors = []
    for column in spec.columns:
        if not column.name.endswith("_x_mm"):
            continue
        prefix = column.name[: -len("_x_mm")]
        position = (f"{prefix}_x_mm", f"{prefix}_y_mm", f"{prefix}_z_mm")
        orientation = _orientation(prefix, names)
        if names.issuperset(position) and orientation is not None:
            sensors.append(SensorColumns(prefix, position, orientation, column.frame or spec.name))
    return sensors


def stream_json_schema(spec: StreamSpec) -> dict[str, Any]:
    """The JSON Schema of topic ``/<stream>``: one single-typed property per column (with its unit,
    dtype and description), ``seq`` and ``t_host_ns`` required, other columns left out when missing."""
    properties = {}
    for column in spec.columns:
        facts = {"unit": column.unit, **{k: v for k, v in column.to_manifest().items() if k != "name"}}
        properties[column.name] = {"type": JSON_TYPES.get(column.dtype, "number"), **facts}
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": f"midas.{spec.name}",
            "description": spec.description, "type": "object", "properties": properties,
            "required": [name for name in REQUIRED if name in properties]}


def json_row(names: Sequence[str], values: Sequence[Any]) -> bytes:
    """One row as a JSON message: missing values (None, NaN) left out, numbers exactly as given."""
    row = {name: value for name, value in zip(names, values) if value is not None and value == value}  # NaN != NaN
    return json.dumps(row, separators=(",", ":")).encode()


def timestamp(t_ns: int) -> Any:
    """A ``foxglove`` Timestamp from host nanoseconds."""
    from foxglove.messages import Timestamp

    return Timestamp(int(t_ns) // 1_000_000_000, int(t_ns) % 1_000_000_000)


Pose = tuple[Sequence[float], Sequence[float]]  # position (m) x, y, z; quaternion x, y, z, w


def sensor_poses(sensor: SensorColumns, table: dict[str, np.ndarray]) -> list[Pose | None]:
    """Each row's pose of one sensor from column arrays (mm; deg or quaternion): position in metres and
    unit quaternion, None where a value is missing (or the quaternion is zero)."""
    position_mm = np.column_stack([np.asarray(table[c], dtype=np.float64) for c in sensor.position])
    orientation = np.column_stack([np.asarray(table[c], dtype=np.float64) for c in sensor.orientation])
    if orientation.shape[1] == 3:
        quaternions = quaternions_from_angles(orientation)
    else:
        with np.errstate(divide="ignore", invalid="ignore"):  # a zero quaternion: inf/NaN, left out below
            quaternions = orientation / np.linalg.norm(orientation, axis=1, keepdims=True)
    positions = position_mm / 1000.0
    complete = (np.isfinite(positions).all(axis=1) & np.isfinite(quaternions).all(axis=1)).tolist()
    return [(p, q) if ok else None for p, q, ok in zip(positions.tolist(), quaternions.tolist(), complete)]


def transforms_message(stream: str, sensors: Sequence[SensorColumns], t_ns: int,
                       poses: Sequence[Pose | None]) -> Any:
    """The ``foxglove.FrameTransforms`` of one row from each sensor's pose (None: left out); None when no
    sensor has one."""
    from foxglove.messages import FrameTransform, FrameTransforms, Quaternion, Vector3

    stamp = timestamp(t_ns)
    transforms = []
    for sensor, pose in zip(sensors, poses):
        if pose is None:
            continue
        (x, y, z), (qx, qy, qz, qw) = pose
        transforms.append(FrameTransform(timestamp=stamp, parent_frame_id=sensor.parent_frame,
                                         child_frame_id=f"{stream}/{sensor.name}",
                                         translation=Vector3(x=x, y=y, z=z), rotation=Quaternion(x=qx, y=qy, z=qz, w=qw)))
    return FrameTransforms(transforms=transforms) if transforms else None


def marker_log(t_ns: int, text: Any, source: Any) -> Any:
    """An operator's marker as a ``foxglove.Log`` (level info, ``name`` = where it came from)."""
    from foxglove.messages import Log, LogLevel

    return Log(timestamp=timestamp(t_ns), level=LogLevel.Info, message="" if text is None else str(text),
               name="" if source is None else str(source))
