"""`midas record --foxglove [HOST:PORT]`: the live streams over the Foxglove WebSocket protocol.

One ``foxglove-sdk`` WebSocket server per recording, in the recorder's process (default
127.0.0.1:8765, loopback only: reach it from another machine through an SSH tunnel). Rows never reach
the recorder (the workers write them and send bookkeeping only, record/worker.py), but each
bookkeeping batch carries its last row (``DataBatch.last_row``, what the live screen shows): that row
is published, so the live view is every stream thinned to one row per worker batch (a few per
second to the stream's full rate, depending on how the device delivers), never more than the disk
holds and never in the workers' way. Publishing costs nothing while no client is subscribed. The
operator's markers are published once fsynced (record/markers.py ``MarkerLog(publish=...)``).

Topics and messages are those of the MCAP export (interop/foxglove_topics.py): ``/<stream>`` JSON,
``/events`` as ``foxglove.Log``, ``/<stream>/transforms`` for EmHT and robot arms.
Publishing never stops a recording: a failure is one warning and that stream is no longer published.
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Sequence

import numpy as np

from midas_cli.errors import ConfigError
from midas_cli.interop.foxglove_topics import (json_row, marker_log, transforms_message,
                                               sensor_columns, sensor_poses, stream_json_schema)
from midas_cli.record.markers import EVENTS_STREAM
from midas_cli.session.schema import StreamSpec

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
DEFAULT_ADDRESS = f"{DEFAULT_HOST}:{DEFAULT_PORT}"


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT``, ``HOST`` or ``:PORT`` (defaults 127.0.0.1 and 8765); ConfigError otherwise."""
    host, separator, port = text.strip().rpartition(":")
    if not separator:
        host, port = text.strip(), ""
    host = host.strip("[]") or DEFAULT_HOST
    if not port:
        return host, DEFAULT_PORT
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"--foxglove-address {text!r}: expected HOST:PORT with a port 1..65535")
    return host, int(port)


class _StreamTopics:
    """The channels of one stream on the live server."""

    def __init__(self, spec: StreamSpec, context: Any) -> None:
        from foxglove import Channel
        from foxglove.channels import FrameTransformsChannel, LogChannel

        self.spec = spec
        self.markers = spec.name == EVENTS_STREAM and {"text", "source"} <= set(spec.column_names)
        self.rows: Any = LogChannel(f"/{spec.name}", context=context) if self.markers else \
            Channel(f"/{spec.name}", schema=stream_json_schema(spec), context=context)
        self.sensors = sensor_columns(spec)
        self.transforms = FrameTransformsChannel(f"/{spec.name}/transforms", context=context) if self.sensors else None

    def publish(self, row: Sequence[Any]) -> None:
        """One row (seq, t_host_ns, ...) to every topic of the stream that has a subscriber."""
        names = self.spec.column_names
        t_ns = int(row[1])
        if self.rows.has_sinks():
            values = dict(zip(names, row))
            message = marker_log(t_ns, values.get("text"), values.get("source")) if self.markers \
                else json_row(names, row)
            self.rows.log(message, log_time=t_ns)
        if self.transforms is not None and self.transforms.has_sinks():
            table = {name: np.array([np.nan if value is None else value], dtype=np.float64)
                     for name, value in zip(names, row) if not isinstance(value, str)}
            message = transforms_message(self.spec.name, self.sensors, t_ns,
                                         [sensor_poses(sensor, table)[0] for sensor in self.sensors])
            if message is not None:
                self.transforms.log(message, log_time=t_ns)


class FoxgloveLive:
    """The recording's WebSocket server and its channels; ``publish`` never raises."""

    def __init__(self, address: str, specs: Sequence[StreamSpec], name: str,
                 warn: Callable[[str], None] = lambda message: log.warning("%s", message)) -> None:
        import foxglove

        host, port = parse_address(address)
        self.warn = warn
        self.context = foxglove.Context()  # this recording's channels only
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context)
        except RuntimeError as exc:  # the SDK's FoxgloveError: address in use, cannot bind
            raise ConfigError(f"--foxglove on {host}:{port}: {exc}") from exc
        self.address = f"{host}:{self.server.port}"
        self.topics = {spec.name: _StreamTopics(spec, self.context) for spec in specs}
        self.failed: set[str] = set()

    def publish(self, spec: StreamSpec, rows: Sequence[Sequence[Any]]) -> None:
        """The last of ``rows`` (already on disk) of stream ``spec``; a failure is one warning and the
        stream is published no more."""
        topics = self.topics.get(spec.name)
        if topics is None or spec.name in self.failed or not rows:
            return
        try:
            topics.publish(rows[-1])
        except Exception as exc:  # noqa: BLE001 - the recording goes on; the stream stops being published
            self.failed.add(spec.name)
            self.warn(f"--foxglove: {spec.name} is no longer published: {exc}")

    def close(self) -> None:
        """Stop the server (clients see it close)."""
        self.server.stop()
