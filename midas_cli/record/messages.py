"""Messages from device workers to the recorder (plain dataclasses: they cross processes).

Workers write their rows to the stream files themselves; what they send is bookkeeping only."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class DataBatch:
    """Rows of one stream that are already on disk (handed to the OS by the worker).

    ``seq``/``t_host_ns`` repeat the rows' first two columns and ``committed_ns`` is, per row, the
    host-clock time (Unix-epoch ns) its append returned: int64 arrays of shape (rows,).
    ``nbytes`` is what the appends wrote, ``write_ns`` the time they took (ns: the disk's share
    of the latency), ``corrupt`` the worker's running total of corrupt records for the device."""

    device: str
    stream: str
    seq: np.ndarray
    t_host_ns: np.ndarray
    committed_ns: np.ndarray
    last_row: tuple
    nbytes: int
    write_ns: int
    corrupt: int

    def merged(self, later: "DataBatch") -> "DataBatch":
        """This batch followed by ``later`` (same stream): how a message the queue refused is kept."""
        return DataBatch(self.device, self.stream, np.concatenate([self.seq, later.seq]),
                         np.concatenate([self.t_host_ns, later.t_host_ns]),
                         np.concatenate([self.committed_ns, later.committed_ns]), later.last_row,
                         self.nbytes + later.nbytes, self.write_ns + later.write_ns, later.corrupt)


@dataclass
class DeviceEvent:
    """A change of a device's state: opened, open_failed, lost, finished, crashed, write_failed,
    exited. ``write_failed`` carries ``info={"stream": name, "rows": n}``: rows read but not written."""

    device: str
    event: str
    t_host_ns: int
    message: str = ""
    info: dict[str, Any] = field(default_factory=dict)
