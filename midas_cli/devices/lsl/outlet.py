"""Publish a midas stream as an LSL outlet: the one place that turns a ``StreamSpec`` into a StreamInfo.

Used by ``midas replay --to lsl`` (interop/lsl_replay.py), ``midas record --lsl-out`` (record/lsl_out.py,
the operator's markers included) and, for the same names and channels, ``midas export --format xdf``
(interop/xdf.py), so a consumer sees the same stream either way, and LabRecorder recording a replay
gets what the XDF export holds. The field's conventions (the XDF meta-data specification):

* name = the stream's name; type = ``Markers`` for the operator's markers (a stream with a text
  column), ``MoCap`` for motion capture (EmHT, hand keypoints), else the device's kind;
  ``source_id`` = ``midas:<session>:<stream>`` everywhere (stable: a consumer that resolves by
  source_id finds the stream again after a restart);
* numeric streams: ``channel_format`` ``double64`` (ints are exact below 2**53; a missing value is
  NaN), one channel per column but ``t_host_ns`` (the time is the sample's timestamp): ``seq`` first,
  the device's own counter (the video's frame index, gaps = lost samples), then the data columns;
* marker streams: ONE ``string`` channel, the marker's text (marker-aware readers skip marker streams
  with more channels): the stream's ``marker`` column (``gestures_live``: ``decoded``, the cleaned-up
  gesture), else its first text column; the other columns (the operator's markers: ``seq``, the sample
  order, and ``source``, key / mark / ctl) stay in the session's files, as ``<desc><midas><not_sent>`` says;
* ``nominal_srate`` = the manifest's nominal rate, 0 (irregular) for an event stream;
* ``<desc><channels><channel><label/><unit/><type/><description/></channel>...`` from the columns,
  ``<acquisition><manufacturer>midas</manufacturer>``, ``<midas><session/><stream/></midas>``.

Exposure: liblsl binds every outlet's TCP data port and UDP service port to all network interfaces
(IPv4 and IPv6), whatever its configuration file says; that file (``lsl_api.cfg``, see
:func:`lsl_config_file`) can only narrow discovery (``ResolveScope``, ``ListenAddress``, ``IPv6``).
midas leaves it to the user and says which file applies (:func:`exposure_note`).

Times: a midas host time (Unix-epoch ns from CLOCK_MONOTONIC + the session's anchor, clock.py) is on
the LSL clock (``pylsl.local_clock()`` = CLOCK_MONOTONIC) at ``(t_host_ns - anchor_ns) / 1e9`` s.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

from midas_cli.devices.lsl.device import import_pylsl
from midas_cli.session.schema import T_HOST, Column, StreamSpec

CONFIG_ENV = "LSLAPICFG"
CONFIG_PLACES = ("lsl_api.cfg", "~/lsl_api/lsl_api.cfg", "/etc/lsl_api/lsl_api.cfg")  # after $LSLAPICFG
CHANNEL_FORMAT = "double64"
TEXT_CHANNEL_FORMAT = "string"
MARKERS_TYPE = "Markers"
MOCAP_KINDS = ("emht", "handkp")  # device kinds whose streams are typed MoCap


def channel_format(spec: StreamSpec) -> str:
    """``string`` for a stream with a text column, else ``double64``."""
    return TEXT_CHANNEL_FORMAT if spec.has_text else CHANNEL_FORMAT


def source_id(session: str, stream: str) -> str:
    """The outlet's stable ``source_id`` for ``stream`` of session ``session`` (its folder name)."""
    return f"midas:{session}:{stream}"


def stream_type(spec: StreamSpec, kind: str) -> str:
    """The LSL/XDF content type of ``spec`` from a device of kind ``kind`` (see the module docstring)."""
    if spec.has_text:
        return MARKERS_TYPE
    return "MoCap" if kind in MOCAP_KINDS else (kind or spec.device)


def channel_columns(spec: StreamSpec) -> tuple[Column, ...]:
    """The columns sent as channels, in order (see the module docstring)."""
    marker = spec.marker_column
    if marker is not None:
        return (marker,)
    return tuple(c for c in spec.columns if c.name != T_HOST.name)


def stream_info(spec: StreamSpec, kind: str, session: str) -> Any:
    """The ``pylsl.StreamInfo`` describing ``spec`` (device kind ``kind``) of session ``session``."""
    pylsl = import_pylsl()
    columns = channel_columns(spec)
    info = pylsl.StreamInfo(spec.name, stream_type(spec, kind), len(columns), spec.nominal_rate_hz or 0.0,
                            channel_format(spec), source_id(session, spec.name))
    desc = info.desc()
    channels = desc.append_child("channels")
    for column in columns:
        channel = channels.append_child("channel")
        channel.append_child_value("label", column.name)
        channel.append_child_value("unit", column.unit)
        channel.append_child_value("type", column.dtype)
        if column.description:
            channel.append_child_value("description", column.description)
    desc.append_child("acquisition").append_child_value("manufacturer", "midas")
    midas = desc.append_child("midas")
    midas.append_child_value("session", session)
    midas.append_child_value("stream", spec.name)
    not_sent = [c.name for c in spec.columns if c not in columns and c.name != T_HOST.name]
    if not_sent:
        midas.append_child_value("not_sent", ",".join(not_sent))
    return info


def open_outlet(spec: StreamSpec, kind: str, session: str) -> Any:
    """A ``pylsl.StreamOutlet`` for ``spec`` (discoverable from now on)."""
    return import_pylsl().StreamOutlet(stream_info(spec, kind, session))


def row_values(spec: StreamSpec, rows: Sequence[Sequence[Any]]) -> list[list[Any]]:
    """The channel values of ``rows`` (full rows: seq, t_host_ns, ...) as the stream's CSV holds them:
    a float rounded to its column's decimals (``round`` and the CSV's ``{:.Nf}`` round alike), an int
    as an int; None -> NaN (a marker's text as it is, None -> ""). A live consumer sees what a later
    replay of the file sends."""
    columns = channel_columns(spec)
    at = [spec.column_names.index(c.name) for c in columns]
    if spec.has_text:
        return [["" if row[i] is None else str(row[i]) for i in at] for row in rows]
    digits = [None if c.dtype == "int" else c.decimals for c in columns]
    return [[math.nan if row[i] is None else float(int(row[i])) if d is None else round(float(row[i]), d)
             for i, d in zip(at, digits)] for row in rows]


def lsl_seconds(t_host_ns: int, anchor_ns: int) -> float:
    """A host time (ns) on the local LSL clock (s)."""
    return (t_host_ns - anchor_ns) / 1e9


def lsl_config_file(environ: Mapping[str, str] | None = None) -> Path | None:
    """The one ``lsl_api.cfg`` liblsl (1.16 to 1.18) loads in this process: the first readable file of
    ``$LSLAPICFG``, ``./lsl_api.cfg``, ``~/lsl_api/lsl_api.cfg``, ``/etc/lsl_api/lsl_api.cfg``; None
    when there is none (liblsl's built-in defaults)."""
    environ = os.environ if environ is None else environ
    named = [Path(environ[CONFIG_ENV])] if environ.get(CONFIG_ENV) else []  # taken as is, no ~ expansion
    for path in named + [Path(place).expanduser() for place in CONFIG_PLACES]:
        if path.is_file() and os.access(path, os.R_OK):
            return path.absolute()
    return None


def exposure_note(config: Path | None) -> str:
    """One line for stderr when outlets are about to exist: who can reach them, and which liblsl
    configuration applies (``config``, from :func:`lsl_config_file`)."""
    applied = (f"liblsl configuration {config}" if config
               else "no lsl_api.cfg: liblsl's defaults, discoverable across the site")
    return (f"LSL outlets accept connections on every network interface ({applied}); README 'Live streams "
            f"out' says how to keep them on this machine")
