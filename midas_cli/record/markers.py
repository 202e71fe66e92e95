"""The operator's markers: the session's ``events`` stream (seq, t_host_ns, text, source).

A marker is a line of text the operator adds while recording: from the live screen (key ``m``, source
``key``), from another shell (`midas mark`, source ``mark``) or over the control socket (`midas ctl mark`,
source ``ctl``). Its time is the host clock (the clock of every stream) when the recorder took it; the
row is written and fsynced before the marker is acknowledged. The stream is an event stream: no
nominal rate, it never degrades anything. Markers are taken only between the session's start and the
moment the recorder starts to stop, so every one lies within the session's span.
"""

from __future__ import annotations

import threading
from typing import Any, Callable, Iterable, Optional

from midas_cli.clock import HostClock
from midas_cli.errors import ConfigError, SessionError
from midas_cli.session.csvtext import control_characters
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
from midas_cli.session.writer import SessionWriter

EVENTS_STREAM = "events"
EVENTS_DEVICE = "operator"
SOURCES = ("key", "mark", "ctl")
MAX_TEXT = 1000  # characters


def events_spec() -> StreamSpec:
    """The ``events`` stream's layout."""
    return StreamSpec(EVENTS_STREAM, EVENTS_DEVICE, (
        SEQ, T_HOST,
        Column("text", "text", description="the operator's marker text (one line)"),
        Column("source", "text", description="where it came from: key (live screen), mark (`midas mark`), "
                                             "ctl (`midas ctl`)"),
    ), None, "operator markers and remote-control events (host clock)")


def check_stream_names(device_streams: Iterable[str]) -> None:
    """ConfigError if a device's stream would take the events stream's name."""
    if EVENTS_STREAM in set(device_streams):
        raise ConfigError(f"a device stream is named {EVENTS_STREAM!r}, which holds the operator's markers: "
                          f"rename that device")


def check_marker_text(text: str) -> str:
    """``text`` without surrounding spaces; ConfigError if it is empty, too long or not one line."""
    text = str(text).strip()
    if not text:
        raise ConfigError("a marker needs some text, got an empty one")
    if len(text) > MAX_TEXT:
        raise ConfigError(f"a marker holds at most {MAX_TEXT} characters, got {len(text)}")
    bad = control_characters(text)
    if bad:
        raise ConfigError(f"a marker is one line of text without control characters, got {', '.join(bad)}")
    return text


class MarkerLog:
    """Appends markers to the session's events stream (thread-safe; the control socket's thread and the
    keyboard's both call ``add``). ``publish(spec, rows)``, when given (``--lsl-out``), gets each row
    once it is on disk and must never raise (record/lsl_out.py ``LiveOutlets.publish``)."""

    def __init__(self, writer: SessionWriter, clock: HostClock,
                 publish: Optional[Callable[[StreamSpec, list[tuple]], None]] = None) -> None:
        self.writer = writer
        self.clock = clock
        self.publish = publish
        self.spec = writer.specs[EVENTS_STREAM]
        self.count = 0
        self.last: dict[str, Any] | None = None
        self._last_ns = 0
        self._closed = False
        self._lock = threading.Lock()

    def add(self, text: str, source: str) -> dict[str, Any]:
        """Write one marker now (fsynced) and return its row as a dict. ConfigError for bad text or
        source; SessionError once the recording is stopping."""
        text = check_marker_text(text)
        if source not in SOURCES:
            raise ConfigError(f"marker source must be one of {', '.join(SOURCES)}, got {source!r}")
        with self._lock:
            if self._closed:
                raise SessionError("the recording is stopping; the marker was not written")
            t_host_ns = max(self.clock.now_ns(), self._last_ns + 1)  # strictly increasing
            rows = [(self.count, t_host_ns, text, source)]
            self.writer.append(EVENTS_STREAM, self.spec.format_rows(rows))
            self.writer.sync_stream(EVENTS_STREAM)
            if self.publish is not None:
                self.publish(self.spec, rows)
            row = {"seq": self.count, "t_host_ns": t_host_ns, "text": text, "source": source}
            self.count += 1
            self._last_ns = t_host_ns
            self.last = row
        return row

    def close(self) -> None:
        """No marker after this (called before the recorder takes its stop time)."""
        with self._lock:
            self._closed = True
