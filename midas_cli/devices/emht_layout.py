"""The EmHT stream layout, one place for every EmHT backend (``sim://emht``, ``fob://``, ``atc3dg://``).

A row is ``seq, t_host_ns, t_device_s``, then per sensor x/y/z (mm, transmitter frame),
azimuth/elevation/roll (deg) and quality (distortion metric, 0 = best); fields a backend cannot fill
are empty. Also the sequence numbering the real trackers share: on every (re)open ``seq`` starts from
the number of cycles the session has lasted at the nominal rate, never below where the previous
connection of the device stopped (kept in the worker's :class:`~midas_cli.devices.base.DeviceContext`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from midas_cli.devices.base import DeviceContext
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
from midas_cli.synthetic.hands import SENSOR_NAMES

MAX_SENSORS = 4
DESCRIPTION = "6-DoF pose per sensor, one row per synchronous record of all sensors"
VALUES_PER_SENSOR = 7  # x, y, z, azimuth, elevation, roll, quality


def emht_columns(sensors: int) -> tuple[Column, ...]:
    """Columns of an EmHT stream with ``sensors`` sensors (1..4)."""
    columns = [SEQ, T_HOST, Column("t_device_s", "float", "s", 6, clock="device")]
    for s in range(1, sensors + 1):
        where = SENSOR_NAMES[s - 1]
        columns += [Column(f"s{s}_{a}_mm", "float", "mm", 3, frame="emht_transmitter",
                           description=f"sensor {s} ({where}) position") for a in "xyz"]
        columns += [Column(f"s{s}_{a}_deg", "float", "deg", 3, description=f"sensor {s} ({where}) {a}")
                    for a in ("azimuth", "elevation", "roll")]
        columns.append(Column(f"s{s}_quality", "float", "", 3, description="distortion metric, 0 = best"))
    return tuple(columns)


def emht_stream(name: str, sensors: int, rate_hz: float, description: str = DESCRIPTION) -> StreamSpec:
    """The stream of EmHT device ``name`` (the stream is named after the device)."""
    return StreamSpec(name, name, emht_columns(sensors), rate_hz, description)


@dataclass
class SeqResume:
    """Where a device's ``seq`` resumes after a reconnect (carried by the worker's context)."""

    next_seq: int = 0


def resume_seq(context: DeviceContext, name: str) -> SeqResume:
    return context.carry(f"{name}/emht-seq", SeqResume)


def first_seq(context: DeviceContext, name: str, rate_hz: float) -> int:
    """Where a (re)opened device's seq starts: cycles since the session start at the nominal rate, never
    below where the previous connection of device ``name`` (in this context) stopped."""
    elapsed_ns = max(0, context.clock.now_ns() - context.start_ns)
    return max(int(math.ceil(elapsed_ns * rate_hz / 1e9)), resume_seq(context, name).next_seq)
