"""``lsl://?name=NAME&type=TYPE&source_id=ID``: record one Lab Streaming Layer stream.

The stream is found by its properties (all given ones must match; at least one is required) within
``timeout`` seconds, once when the recording is planned (its channel count and labels make the
columns) and again by the worker. pylsl is imported only when an lsl:// device is used.

Streams, raw times only (DESIGN.md section 4; pyxdf's model):
  * ``<name>``: ``seq`` (samples received, continued across reconnects), ``t_host_ns`` (host clock
    when pulled), ``t_lsl_s`` (the sample's timestamp on the *sender's* LSL clock), one column per
    channel (the stream's channel labels when they are usable names, else ch1..chN).
  * ``<name>_clock``: every ``clock_every`` s one clock-offset probe: ``local_clock_s`` (this host's
    LSL clock = CLOCK_MONOTONIC, so host ns = local_clock_s * 1e9 + the session's clock anchor) and
    ``offset_s`` from ``inlet.time_correction()``: sender time + offset = this host's LSL clock. ``align``
    maps t_lsl_s onto the host clock with these probes (a linear fit, as pyxdf's clock sync does).

Only numeric channel formats fit the session's CSV schema; string streams (markers) are refused.
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass
from typing import Any

from midas_cli.devices.base import Device, DeviceContext, DeviceUrl
from midas_cli.errors import ConfigError, DeviceError
from midas_cli.session.device_files import last_recorded_seq
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec

log = logging.getLogger(__name__)

PARAMS = {"name": str, "type": str, "source_id": str, "hostname": str, "timeout": float, "clock_every": float,
          "rate": float}
DEFAULTS = {"name": "", "type": "", "source_id": "", "hostname": "", "timeout": 5.0, "clock_every": 1.0, "rate": 0.0}
MATCH_KEYS = ("name", "type", "source_id", "hostname")
MAX_CHUNK = 4096
POLL_S = 0.005
INT_FORMATS = {"int8", "int16", "int32", "int64"}
_LABEL_OK = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,40}$")
RESERVED_LABELS = {"seq", "t_host_ns", "t_lsl_s"}  # the columns every lsl:// stream starts with
CF_NAMES = {1: "float32", 2: "double64", 3: "string", 4: "int32", 5: "int16", 6: "int8", 7: "int64"}


def import_pylsl():
    """pylsl, or a DeviceError saying how to install it."""
    try:
        import pylsl
    except ImportError as exc:
        raise DeviceError(f"lsl:// needs pylsl (pip install pylsl==1.18.6, its wheel bundles liblsl): {exc}") from None
    return pylsl


@dataclass(frozen=True)
class LslLayout:
    """What the recorded columns depend on: channel count, labels and format, nominal rate."""

    channels: int
    labels: tuple[str, ...]
    channel_format: str
    nominal_srate: float
    source_id: str
    hostname: str


def predicate(params: dict[str, Any], raw: str) -> str:
    """The XPath predicate that selects the stream, e.g. ``name='HR' and type='ECG'``."""
    parts = []
    for key in MATCH_KEYS:
        value = params[key]
        if value and ("'" in value or '"' in value):
            raise ConfigError(f"{raw}: {key}={value!r} may not contain quotes")
        if value:
            parts.append(f"{key}='{value}'")
    if not parts:
        raise ConfigError(f"{raw}: say which LSL stream to record, e.g. lsl://?name=HeartRate or ?type=ECG")
    return " and ".join(parts)


def resolve(params: dict[str, Any], raw: str):
    """(resolved StreamInfo, its full StreamInfo with <desc>) of the one stream matching the URL;
    DeviceError if none or several. Inlets are made from the resolved one (it carries the endpoints)."""
    pylsl = import_pylsl()
    query = predicate(params, raw)
    found = pylsl.resolve_bypred(query, 1, params["timeout"])
    if not found:
        raise DeviceError(f"{raw}: no LSL stream matches {query} within {params['timeout']:g} s (is the sender "
                          f"running on a reachable host? `python -m pylsl.examples.ReceiveData` lists streams)")
    time.sleep(min(0.2, params["timeout"]))  # let a second matching stream answer too, to refuse ambiguity
    found = pylsl.resolve_bypred(query, 2, 0.2) or found
    ids = {(info.source_id(), info.hostname(), info.uid()) for info in found}
    if len(ids) > 1:
        raise DeviceError(f"{raw}: {len(ids)} LSL streams match {query}; add source_id=... or hostname=...")
    return found[0], full_info(pylsl, found[0], params["timeout"], raw)


def full_info(pylsl, info, timeout: float, raw: str):
    """The stream's complete StreamInfo, with its <desc> (channel labels); a resolve gives only the header."""
    inlet = pylsl.StreamInlet(info, recover=False)
    try:
        return inlet.info(timeout=timeout)
    except pylsl.util.TimeoutError:
        raise DeviceError(f"{raw}: LSL stream {info.name()!r} did not send its description "
                          f"within {timeout:g} s") from None
    finally:
        inlet.close_stream()


def layout_of(info) -> LslLayout:
    """Columns-relevant facts of a StreamInfo; ConfigError for string streams."""
    fmt = CF_NAMES.get(info.channel_format(), str(info.channel_format()))
    if fmt == "string":
        raise ConfigError(f"LSL stream {info.name()!r} carries strings (markers); midas streams hold numbers only")
    labels = channel_labels(info)
    return LslLayout(info.channel_count(), labels, fmt, info.nominal_srate(), info.source_id(), info.hostname())


def channel_labels(info) -> tuple[str, ...]:
    """Labels from the stream's <desc><channels> when each is a usable, unique column name; one that is
    one of the recorder's own columns (seq, t_host_ns, t_lsl_s: a midas outlet sends its own ``seq``, a
    replayed lsl:// session a t_lsl_s) is kept as ``src_<label>``; else ch1..chN."""
    count = info.channel_count()
    labels, channel = [], info.desc().child("channels").child("channel")
    while not channel.empty() and len(labels) < count:
        label = channel.child_value("label")
        labels.append(f"src_{label}" if label in RESERVED_LABELS else label)
        channel = channel.next_sibling()
    usable = all(_LABEL_OK.match(x) and x not in RESERVED_LABELS for x in labels)
    if len(labels) == count and len(set(labels)) == count and usable:
        return tuple(labels)
    return tuple(f"ch{i}" for i in range(1, count + 1))


class LslDevice(Device):
    """An LSL inlet plus periodic clock-offset probes."""

    kind = "lsl"

    def __init__(self, name: str, url: DeviceUrl, context: DeviceContext) -> None:
        super().__init__(name, url)
        self.params = url.take(PARAMS, DEFAULTS)
        predicate(self.params, url.raw)
        if self.params["clock_every"] <= 0 or self.params["timeout"] <= 0 or self.params["rate"] < 0:
            raise ConfigError(f"{url.raw}: timeout and clock_every must be > 0 s, rate >= 0 Hz")
        self.clock = context.clock
        self.session_dir = context.session_dir
        self.info, full = resolve(self.params, url.raw)
        self.layout = layout_of(full)
        self.inlet = None
        self._seq = 0
        self._probe_seq = 0
        self._next_probe = 0.0
        self._last_t = 0

    @property
    def rate(self) -> float | None:
        """Nominal rate: the stream's, or ``rate`` for irregular streams; None (an event stream, e.g.
        markers) when the stream is irregular and no ``rate`` is given."""
        return self.layout.nominal_srate or self.params["rate"] or None

    @property
    def streams(self) -> list[StreamSpec]:
        dtype = "int" if self.layout.channel_format in INT_FORMATS else "float"
        columns = [SEQ, T_HOST, Column("t_lsl_s", "float", "s", 6, clock="device",
                                       description="sample timestamp on the sender's LSL clock")]
        columns += [Column(label, dtype, "", 6, description=f"LSL channel {i + 1}")
                    for i, label in enumerate(self.layout.labels)]
        probe = (SEQ, T_HOST,
                 Column("local_clock_s", "float", "s", 6, clock="device", description="this host's LSL clock"),
                 Column("offset_s", "float", "s", 6, description="time_correction: sender clock + offset = local"))
        return [StreamSpec(self.name, self.name, tuple(columns), self.rate,
                           f"LSL stream {self.info.name()!r} ({self.info.type()})"),
                StreamSpec(f"{self.name}_clock", self.name, probe, 1.0 / self.params["clock_every"],
                           "LSL clock-offset probes for align")]

    def settings(self) -> dict[str, Any]:
        return {**{k: v for k, v in self.params.items() if v != ""}, "lsl_name": self.info.name(),
                "lsl_type": self.info.type(), "channels": self.layout.channels,
                "channel_format": self.layout.channel_format, "nominal_srate": self.layout.nominal_srate}

    def open(self) -> dict[str, Any]:
        pylsl = import_pylsl()
        if self.session_dir:
            self._seq = _next_seq(self.session_dir, self.name)
            self._probe_seq = _next_seq(self.session_dir, f"{self.name}_clock")
        self.inlet = pylsl.StreamInlet(self.info, max_buflen=360, recover=False)
        try:
            self.inlet.open_stream(timeout=self.params["timeout"])
            full = self.inlet.info(timeout=self.params["timeout"])
        except pylsl.util.TimeoutError:
            self.close()
            raise DeviceError(f"{self.name}: LSL stream {self.info.name()!r} did not answer within "
                              f"{self.params['timeout']:g} s") from None
        if layout_of(full).channels != self.layout.channels:
            self.close()
            raise DeviceError(f"{self.name}: LSL stream {self.info.name()!r} changed its channel count")
        return {"model": f"LSL {full.type()} stream {full.name()!r}", "source_id": full.source_id(),
                "hostname": full.hostname(), "uid": full.uid(), "created_at_s": full.created_at(),
                "lsl_library": pylsl.library_version(), "lsl_clock": "CLOCK_MONOTONIC (pylsl.local_clock)",
                "host_ns_from_local_clock": "local_clock_s * 1e9 + clock.anchor_ns"}

    def read(self) -> dict[str, list[tuple]]:
        if self.inlet is None:
            raise DeviceError(f"{self.name}: read before open")
        pylsl = import_pylsl()
        rows: dict[str, list[tuple]] = {}
        try:
            samples, stamps = self.inlet.pull_chunk(timeout=POLL_S, max_samples=MAX_CHUNK)
            if time.monotonic() >= self._next_probe:
                rows[f"{self.name}_clock"] = [self._probe()]
        except pylsl.util.LostError:
            raise DeviceError(f"{self.name}: LSL stream {self.info.name()!r} was lost (sender stopped?)") from None
        except pylsl.util.TimeoutError:
            raise DeviceError(f"{self.name}: LSL clock probe of {self.info.name()!r} timed out") from None
        if samples:
            rows[self.name] = [self._row(sample, stamp) for sample, stamp in zip(samples, stamps)]
        return rows

    def _row(self, sample: list, stamp: float) -> tuple:
        t_host = max(self.clock.now_ns(), self._last_t + 1)
        self._last_t = t_host
        self._seq += 1
        return (self._seq - 1, t_host, stamp, *sample)

    def _probe(self) -> tuple:
        offset = self.inlet.time_correction(timeout=self.params["timeout"])
        local = time.monotonic()
        self._next_probe = local + self.params["clock_every"]
        self._probe_seq += 1
        return (self._probe_seq - 1, self.clock.from_monotonic_ns(int(local * 1e9)), local, offset)

    def close(self) -> None:
        if self.inlet is not None:
            self.inlet.close_stream()
            self.inlet = None


def _next_seq(session_dir: str, stream: str) -> int:
    """Where a reopened device continues its counter: after the last recorded row (0 if none)."""
    last = last_recorded_seq(session_dir, stream)
    return 0 if last is None else last + 1
