"""A session as an XDF file, the LSL ecosystem's format, written to the specification
(https://github.com/sccn/xdf/wiki/Specifications, XDF 1.0). No maintained Python XDF writer exists
(pyxdf reads only; LabRecorder is a C++ application), so this writer is small and tested only by reading
its files back with pyxdf.

Layout (all integers little-endian): the magic ``XDF:``, then chunks, each
``[NumLengthBytes: 1 byte, 1|4|8][Length: that many bytes = bytes of tag + content][Tag: uint16][content]``:

* tag 1 FileHeader: XML ``<info><version>1.0</version>...``;
* tag 2 StreamHeader: ``[StreamId: uint32][XML]``, one per midas stream: name, type, ``channel_count``,
  ``nominal_srate`` (the manifest's nominal rate; 0 for an event stream), ``channel_format``,
  ``source_id`` ``midas:<session>:<stream>``, and ``<desc><channels><channel><label/><unit/><type/></channel>...`` from the manifest;
* tag 3 Samples: ``[StreamId: uint32][NumSamples: varlen][samples]``, each sample
  ``[TimeStampBytes: 1 byte = 8][TimeStamp: double, seconds][values]``; a varlen number is
  ``[NumBytes: 1 byte, 1|4|8][the number]``. One Samples chunk per piece of the stream read;
* tag 4 ClockOffset: ``[StreamId: uint32][CollectionTime: double][OffsetValue: double]``;
* tag 6 StreamFooter: ``[StreamId: uint32][XML]``: first/last timestamp, sample count, the clock offsets.

Times: a sample's timestamp is its ``t_host_ns`` / 1e9 (seconds on the session's host clock, the clock
midas stamps every stream with). Every other column is a ``double64`` channel (``t_host_ns`` is the
timestamp, not a channel; int columns are exact below 2**53, a missing value is NaN). Clock offsets: a
midas session has one clock, the host clock of the recording computer (manifest ``clock``); every stream
is already on it, so each offset is 0 s, written at the start, every ``OFFSET_EVERY_S`` and at the stop
(what LabRecorder does for a stream recorded on the recording host), so that pyxdf's synchronisation
leaves the times as they are. Names, types, channels and ``source_id`` are those of the live outlets
(devices/lsl/outlet.py: what LabRecorder would record from `midas replay --to lsl`): the operator's
markers (``streams/events.csv``) are a ``Markers`` stream with one ``string`` channel, the text (a missing
value ""), EmHT and hand keypoints are ``MoCap``. Label sets are ``string`` streams (``labels/<name>``, one channel
``label``, one sample per labelled frame at that frame's host time, ``nominal_srate`` 0).
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any, BinaryIO, Sequence
from xml.sax.saxutils import escape

import numpy as np

from midas_cli import __version__
from midas_cli.devices.lsl.outlet import channel_columns, channel_format, source_id, stream_type
from midas_cli.interop.common import device_kind, frame_clock, json_columns, label_sets
from midas_cli.session.outputs import replacing
from midas_cli.session.reader import Session

MAGIC = b"XDF:"
FILE_HEADER, STREAM_HEADER, SAMPLES, CLOCK_OFFSET, STREAM_FOOTER = 1, 2, 3, 4, 6
OFFSET_EVERY_S = 5.0


def varlen(number: int) -> bytes:
    """The spec's variable-length number: a byte 1, 4 or 8, then the number in that many bytes."""
    if number < 256:
        return struct.pack("<BB", 1, number)
    if number < 2**32:
        return struct.pack("<BI", 4, number)
    return struct.pack("<BQ", 8, number)


def write_chunk(fh: BinaryIO, tag: int, content: bytes) -> None:
    fh.write(varlen(2 + len(content)) + struct.pack("<H", tag) + content)


def _xml(tag: str, fields: dict[str, Any], inner: str = "") -> bytes:
    body = "".join(f"<{k}>{escape(str(v))}</{k}>" for k, v in fields.items())
    return f'<?xml version="1.0"?><{tag}>{body}{inner}</{tag}>'.encode()


def numeric_samples(stream_id: int, times_s: np.ndarray, values: np.ndarray) -> bytes:
    """A Samples chunk's content for ``values`` (N, C) float64 at ``times_s`` (N,)."""
    n, width = values.shape
    packed = np.zeros(n, dtype=np.dtype([("bytes", "u1"), ("t", "<f8"), ("v", "<f8", (width,))], align=False))
    packed["bytes"], packed["t"], packed["v"] = 8, times_s, values
    return struct.pack("<I", stream_id) + varlen(n) + packed.tobytes()


def string_samples(stream_id: int, times_s: Sequence[float], values: Sequence[str]) -> bytes:
    """A Samples chunk's content for a one-channel string stream."""
    return text_samples(stream_id, times_s, [[value] for value in values])


def text_samples(stream_id: int, times_s: Sequence[float], rows: Sequence[Sequence[str]]) -> bytes:
    """A Samples chunk's content for a string stream: ``rows`` (N, C) of text at ``times_s`` (N,)."""
    parts = [struct.pack("<I", stream_id), varlen(len(rows))]
    for t, row in zip(times_s, rows):
        parts.append(struct.pack("<Bd", 8, t))
        for value in row:
            data = value.encode("utf-8")
            parts += [varlen(len(data)), data]
    return b"".join(parts)


class _Stream:
    def __init__(self, fh: BinaryIO, stream_id: int, info: dict[str, Any], channels: list[dict[str, str]]):
        self.fh, self.id, self.count, self.first, self.last = fh, stream_id, 0, None, None
        inner = "<desc><channels>" + "".join(
            "<channel>" + "".join(f"<{k}>{escape(str(v))}</{k}>" for k, v in ch.items()) + "</channel>"
            for ch in channels) + f"</channels><acquisition><manufacturer>midas</manufacturer>" \
            f"<software>midas {escape(__version__)}</software></acquisition></desc>"
        write_chunk(fh, STREAM_HEADER, struct.pack("<I", stream_id) + _xml("info", info, inner))

    def seen(self, times_s: np.ndarray) -> None:
        if len(times_s):
            self.count += len(times_s)
            self.first = float(times_s[0]) if self.first is None else self.first
            self.last = float(times_s[-1])

    def finish(self, offsets_at: np.ndarray) -> None:
        for t in offsets_at:
            write_chunk(self.fh, CLOCK_OFFSET, struct.pack("<Idd", self.id, float(t), 0.0))
        offsets = "".join(f"<offset><time>{t!r}</time><value>0.0</value></offset>" for t in offsets_at.tolist())
        footer = _xml("info", {"first_timestamp": repr(self.first or 0.0), "last_timestamp": repr(self.last or 0.0),
                               "sample_count": self.count}, f"<clock_offsets>{offsets}</clock_offsets>")
        write_chunk(self.fh, STREAM_FOOTER, struct.pack("<I", self.id) + footer)


def write_xdf(session: Session, target: Path) -> dict[str, Any]:
    """Write ``target`` (.xdf); returns samples per stream."""
    start_ns = session.manifest["start"]["host_ns"]
    stop_ns = (session.manifest.get("stop") or {}).get("host_ns", start_ns)
    offsets_at = np.append(np.arange(start_ns / 1e9, stop_ns / 1e9, OFFSET_EVERY_S), stop_ns / 1e9)
    counts: dict[str, int] = {}
    session_id = session.manifest.get("session_id", session.path.name)
    with replacing(target) as tmp, open(tmp, "wb") as fh:
        fh.write(MAGIC)
        write_chunk(fh, FILE_HEADER, _xml("info", {"version": "1.0", "datetime": session.manifest["start"].get("utc", ""),
                                                   "writer": f"midas {__version__}", "session_id": session_id}))
        stream_id = 0
        for name in session.stream_names:
            stream_id += 1
            spec = session.stream_spec(name)
            columns = list(channel_columns(spec))  # as `midas replay` sends them (LabRecorder would get these)
            info = {"name": name, "type": stream_type(spec, device_kind(session, name)),
                    "channel_count": len(columns), "nominal_srate": spec.nominal_rate_hz or 0,
                    "channel_format": channel_format(spec), "source_id": source_id(session_id, name),
                    "version": "1.1", "created_at": start_ns / 1e9,
                    "uid": f"{session_id}/{name}", "session_id": session_id, "hostname": session.manifest.get(
                        "software", {}).get("host", "")}
            stream = _Stream(fh, stream_id, info, [{"label": c.name, "unit": c.unit, "type": c.dtype,
                                                    "description": c.description} for c in columns])
            names = [c.name for c in columns]
            for chunk in session.iter_stream(name):
                times = chunk["t_host_ns"].to_numpy(np.int64) / 1e9
                if spec.has_text:
                    rows = [["" if v is None else str(v) for v in row] for row in zip(*json_columns(chunk[names]))]
                    write_chunk(fh, SAMPLES, text_samples(stream_id, times.tolist(), rows))
                else:
                    values = chunk[names].to_numpy(dtype=np.float64, na_value=np.nan)
                    write_chunk(fh, SAMPLES, numeric_samples(stream_id, times, values))
                stream.seen(times)
            stream.finish(offsets_at)
            counts[name] = stream.count
        for labels in label_sets(session, frame_clock(session)):
            stream_id += 1
            name = f"labels/{labels.name}"
            stream = _Stream(fh, stream_id, {"name": name, "type": "Markers", "channel_count": 1, "nominal_srate": 0,
                                             "channel_format": "string", "source_id": source_id(session_id, name),
                                             "version": "1.1", "created_at": start_ns / 1e9},
                             [{"label": "label", "type": "gesture", "unit": ""}])
            times = labels.t_host_ns / 1e9
            if len(times):
                write_chunk(fh, SAMPLES, string_samples(stream_id, times.tolist(), [str(v) for v in labels.labels]))
            stream.seen(times)
            stream.finish(offsets_at)
            counts[name] = stream.count
    return {"file": str(target), "samples": counts}
