"""Immutable snapshots of a recording's health: what the live TUI, status lines and JSON render.

Acquisition code fills these; renderers (``midas_cli.console``) are pure functions of them.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

STATES = ("starting", "opening", "ok", "degraded", "lost", "stopped")


@dataclass(frozen=True)
class StreamStatus:
    """One stream's live figures. ``latency_ms``: host read -> handed to the OS, cumulative p50/p99/max
    (ms); ``latency_window_ms``: the same over about the last 10 s, with ``n`` (rows in the window)."""

    name: str
    nominal_rate_hz: float | None  # None: an event stream
    measured_rate_hz: float | None
    samples: int
    last_age_s: float | None
    dropped: int
    corrupt: int
    seq_missing: int
    latest: dict[str, float | int | None] = field(default_factory=dict)
    latency_ms: dict[str, float | None] = field(default_factory=dict)
    latency_window_ms: dict[str, float | int | None] = field(default_factory=dict)


@dataclass(frozen=True)
class DeviceStatus:
    name: str
    kind: str
    url: str
    state: str
    reconnects: int
    last_error: str
    streams: tuple[StreamStatus, ...]
    labels: dict[str, str] = field(default_factory=dict)  # channel/sensor number -> name from the rig
    warning: str = ""  # the last warning that does not stop the recording (e.g. --lsl-out)


@dataclass(frozen=True)
class GestureStatus:
    """The live recognition (`record --live-model`): the current (decoded) gesture and its probability, how
    long it has lasted (s, on the frames' clock), the recognition latency of the last frame (ms, time its
    decoded class was decided - frame time) and how long ago that was (s)."""

    label: str
    probability: float
    duration_s: float
    latency_ms: float
    age_s: float


@dataclass(frozen=True)
class RecorderSnapshot:
    session_path: str
    session_id: str
    elapsed_s: float
    duration_s: float | None
    disk_free_bytes: int
    write_rate_bps: float
    bytes_written: int
    devices: tuple[DeviceStatus, ...]
    stopping: bool = False
    recognising: bool = False  # --live-model
    gesture: GestureStatus | None = None  # with --live-model, once a frame was predicted

    def to_json(self) -> dict[str, Any]:
        return asdict(self)
