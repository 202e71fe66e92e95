"""Live per-stream and per-device bookkeeping inside the recorder (main process)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from midas_cli.devices.pedals import DAVINCI_PEDALS
from midas_cli.record.messages import DataBatch
from midas_cli.record.status import StreamStatus
from midas_cli.session.schema import StreamSpec

LATENCY_BIN_NS = 50_000  # 50 us bins
LATENCY_BINS = 100_000  # up to 5 s; the last bin collects anything slower
RATE_WINDOW_NS = 2_000_000_000
LATENCY_WINDOW_S = 10  # the live status's recent-latency window
LATENCY_DEFINITION = ("host read (t_host_ns) -> the device worker's os.write returned (rows handed to the OS), "
                      "upper edge of 50 us bins")


@dataclass
class StreamStats:
    """Counts, rate, latency histogram and sequence accounting of one stream while it records."""

    spec: StreamSpec
    samples: int = 0
    last_seq: int | None = None
    last_t_host_ns: int | None = None
    last_row: tuple | None = None
    dropped: int = 0  # rows read but never written: the append that failed and stopped the recording
    corrupt: int = 0
    missing_outage: int = 0
    missing_unexplained: int = 0
    reopened: bool = False
    latency_hist: np.ndarray = field(default_factory=lambda: np.zeros(LATENCY_BINS, dtype=np.int64))
    latency_max_ns: int = 0
    _recent: deque = field(default_factory=deque)
    _window: deque = field(default_factory=deque)  # (host-clock second, [latency ns arrays]), oldest first

    def add(self, batch: DataBatch, committed_ns: np.ndarray | int) -> None:
        """Account for a batch already on disk; ``committed_ns`` (host clock, per row or one for
        all) is when its append returned, so latency = committed_ns - t_host_ns."""
        self._account_sequence(batch)
        self.samples += len(batch.seq)
        self.last_seq = int(batch.seq[-1])
        self.last_t_host_ns = int(batch.t_host_ns[-1])
        self.last_row = batch.last_row
        self.corrupt = batch.corrupt
        latency = committed_ns - batch.t_host_ns
        bins = np.bincount(np.minimum(latency // LATENCY_BIN_NS, LATENCY_BINS - 1).clip(0))
        self.latency_hist[: len(bins)] += bins
        self.latency_max_ns = max(self.latency_max_ns, int(latency.max()))
        self._remember_recent_latency(latency, int(np.max(committed_ns)) // 1_000_000_000)
        self._recent.append((self.last_t_host_ns, self.samples))
        while self._recent and self._recent[0][0] < self.last_t_host_ns - RATE_WINDOW_NS:
            self._recent.popleft()

    def _account_sequence(self, batch: DataBatch) -> None:
        """Sequence gaps inside a batch or since the last one: an outage if the device reopened in
        between, otherwise unexplained (rows are written before they are accounted, so midas itself
        cannot leave a gap)."""
        steps = np.diff(batch.seq)
        inside = int(np.sum(steps[steps > 1] - 1))
        across = 0 if self.last_seq is None else max(0, int(batch.seq[0]) - self.last_seq - 1)
        if self.reopened:
            self.missing_outage += across
            across = 0
            self.reopened = False
        self.missing_unexplained += inside + across

    def _remember_recent_latency(self, latency_ns: np.ndarray, second: int) -> None:
        """Keep the latencies of the last LATENCY_WINDOW_S whole host-clock seconds, one array per
        second once the second is over (bounded: rate x window values)."""
        if self._window and self._window[-1][0] == second:
            self._window[-1][1].append(latency_ns)
        else:
            if self._window:
                previous, arrays = self._window[-1]
                self._window[-1] = (previous, [np.concatenate(arrays)])
            self._window.append((second, [latency_ns]))
        while self._window[0][0] <= second - LATENCY_WINDOW_S:
            self._window.popleft()

    def measured_rate_hz(self) -> float | None:
        if len(self._recent) < 2:
            return None
        (t0, n0), (t1, n1) = self._recent[0], self._recent[-1]
        return (n1 - n0) / ((t1 - t0) / 1e9) if t1 > t0 else None

    def latency_ms(self) -> dict[str, Any]:
        """Cumulative latency (ms) over the whole recording, from the 50 us histogram."""
        used = self.latency_hist[: min(LATENCY_BINS, self.latency_max_ns // LATENCY_BIN_NS + 1)]  # no row beyond
        total = int(used.sum())
        if not total:
            return {"p50": None, "p95": None, "p99": None, "max": None, "n": 0}
        cumulative = np.cumsum(used)  # the bins up to the slowest row only: the live screen asks 4 times a second
        result: dict[str, Any] = {}
        for name, q in (("p50", 0.50), ("p95", 0.95), ("p99", 0.99)):
            index = int(np.searchsorted(cumulative, q * total))
            result[name] = round((index + 1) * LATENCY_BIN_NS / 1e6, 3)
        result["max"] = round(self.latency_max_ns / 1e6, 3)
        result["n"] = total
        result["definition"] = LATENCY_DEFINITION
        return result

    def latency_window_ms(self, now_ns: int) -> dict[str, Any]:
        """Latency (ms, exact percentiles) of the rows committed in the last ~LATENCY_WINDOW_S s
        (whole seconds of the host clock, ``now_ns`` included): p50, p99, max and n."""
        oldest = now_ns // 1_000_000_000 - LATENCY_WINDOW_S
        recent = [a for second, arrays in self._window if second > oldest for a in arrays]
        if not recent:
            return {"p50": None, "p99": None, "max": None, "n": 0}
        values = np.concatenate(recent) / 1e6
        p50, p99 = np.percentile(values, [50, 99])
        return {"p50": round(float(p50), 3), "p99": round(float(p99), 3), "max": round(float(values.max()), 3),
                "n": int(len(values))}

    def manifest_extra(self) -> dict[str, Any]:
        return {
            "dropped": self.dropped,
            "corrupt": self.corrupt,
            "latency_ms": self.latency_ms(),
            "missing_explained": {"outage": self.missing_outage},
            "missing_unexplained_live": self.missing_unexplained,
        }


@dataclass
class DeviceRecord:
    """A device's identity and history during the recording."""

    name: str
    kind: str
    url: str
    settings: dict[str, Any]
    streams: list[str]
    state: str = "starting"
    info: dict[str, Any] = field(default_factory=dict)
    events: list[dict[str, Any]] = field(default_factory=list)
    opens: int = 0
    last_error: str = ""
    exited: bool = False
    labels: dict[str, str] = field(default_factory=dict)  # channel/sensor number -> name (the live screen)
    priority: dict[str, Any] = field(default_factory=dict)  # what its worker's priority was (record/priority.py)

    @property
    def reconnects(self) -> int:
        return max(0, self.opens - 1)

    @property
    def warning(self) -> str:
        """The last ``warning`` event's message (something degraded that does not stop the recording,
        e.g. a stream --lsl-out could not publish), '' if none."""
        return next((e["message"] for e in reversed(self.events) if e["event"] == "warning"), "")

    def manifest_entry(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "url": self.url,
            "settings": self.settings,
            "streams": self.streams,
            "info": self.info,
            **({"priority": self.priority} if self.priority else {}),
            "reconnects": self.reconnects,
            "events": self.events[-200:],
        }


def device_labels(kind: str, rig_entry: dict[str, Any] | None) -> dict[str, str]:
    """Names of an fps device's channels (the rig's ``pedals`` table, else the paper's da Vinci
    mapping) or an emht device's sensors (the rig's ``sensors``), keyed by the number as text."""
    extras = rig_entry or {}
    if kind == "fps":
        table = extras.get("pedals") or DAVINCI_PEDALS
        return {str(k): str(v) for k, v in table.items()}
    if kind == "emht":
        return {str(k): str(v) for k, v in (extras.get("sensors") or {}).items()}
    return {}


def device_health(record: DeviceRecord, streams: tuple[StreamStatus, ...]) -> str:
    """ok / degraded / lost / starting / stopped, from events and the streams' freshness and rate."""
    if record.state in ("lost", "stopped", "starting", "opening"):
        return record.state
    for stream in streams:
        if stream.nominal_rate_hz is None:  # events: no rate to fall short of, silence is normal
            continue
        stale = max(0.5, 5.0 / stream.nominal_rate_hz)
        if stream.last_age_s is not None and stream.last_age_s > stale:
            return "degraded"
        if stream.measured_rate_hz is not None and stream.measured_rate_hz < 0.9 * stream.nominal_rate_hz:
            return "degraded"
    return "ok"
