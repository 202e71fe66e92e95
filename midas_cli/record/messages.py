"""Messages from device workers to the recorder (plain tuples/dataclasses: they cross processes)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class DataBatch:
    """Rows of one stream, already formatted as CSV lines by the stream's schema.

    ``seq``/``t_host_ns`` repeat the first two columns as int64 arrays for checks and latency;
    ``dropped``/``corrupt`` are the worker's running totals for the device."""

    device: str
    stream: str
    text: str
    seq: np.ndarray
    t_host_ns: np.ndarray
    last_row: tuple
    dropped: int
    corrupt: int


@dataclass
class DeviceEvent:
    """A change of a device's state: opened, open_failed, lost, closed, exited."""

    device: str
    event: str
    t_host_ns: int
    message: str = ""
    info: dict[str, Any] = field(default_factory=dict)
    dropped: int = 0
    corrupt: int = 0
