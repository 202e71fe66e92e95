"""Publish a midas stream as an LSL outlet: the one place that turns a ``StreamSpec`` into a StreamInfo.

Used by ``midas replay --to lsl`` (interop/lsl_replay.py) and ``midas record --lsl-out``
(record/lsl_out.py), so a consumer sees the same stream either way:

* name = the stream's name, type = its device's kind, ``source_id`` = ``midas:<session>:<stream>``
  (stable: a consumer that resolves by source_id finds the stream again after a restart);
* ``channel_format`` ``double64`` (ints are exact below 2**53; a missing value is NaN), one channel per
  data column: every column but ``seq`` and ``t_host_ns`` (a stream with no other column sends its
  ``seq``); a stream with a text column (the operator's ``events``: LSL's marker streams) is ``string``,
  every value as its CSV text (a missing value is "");
* ``nominal_srate`` = the manifest's nominal rate, 0 (irregular) for an event stream;
* ``<desc><channels><channel><label/><unit/><type/><description/></channel>...`` from the columns,
  and ``<acquisition><manufacturer>midas</manufacturer>``.

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
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec

CONFIG_ENV = "LSLAPICFG"
CONFIG_PLACES = ("lsl_api.cfg", "~/lsl_api/lsl_api.cfg", "/etc/lsl_api/lsl_api.cfg")  # after $LSLAPICFG
CHANNEL_FORMAT = "double64"
TEXT_CHANNEL_FORMAT = "string"


def channel_format(spec: StreamSpec) -> str:
    """``string`` for a stream with a text column, else ``double64``."""
    return TEXT_CHANNEL_FORMAT if spec.has_text else CHANNEL_FORMAT


def source_id(session: str, stream: str) -> str:
    """The outlet's stable ``source_id`` for ``stream`` of session ``session`` (its folder name)."""
    return f"midas:{session}:{stream}"


def channel_columns(spec: StreamSpec) -> tuple[Column, ...]:
    """The columns sent as channels, in order (see the module docstring)."""
    data = tuple(c for c in spec.columns if c.name not in (SEQ.name, T_HOST.name))
    return data or (spec.columns[0],)


def stream_info(spec: StreamSpec, kind: str, session: str) -> Any:
    """The ``pylsl.StreamInfo`` describing ``spec`` (device kind ``kind``) of session ``session``."""
    pylsl = import_pylsl()
    columns = channel_columns(spec)
    info = pylsl.StreamInfo(spec.name, kind or spec.device, len(columns), spec.nominal_rate_hz or 0.0,
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
    return info


def open_outlet(spec: StreamSpec, kind: str, session: str) -> Any:
    """A ``pylsl.StreamOutlet`` for ``spec`` (discoverable from now on)."""
    return import_pylsl().StreamOutlet(stream_info(spec, kind, session))


def row_values(spec: StreamSpec, rows: Sequence[Sequence[Any]]) -> list[list[float]]:
    """The channel values of ``rows`` (full rows: seq, t_host_ns, ...) as the stream's CSV holds them:
    a float rounded to its column's decimals (``round`` and the CSV's ``{:.Nf}`` round alike), an int
    as an int; None -> NaN. A live consumer sees what a later replay of the file sends."""
    columns = channel_columns(spec)
    at = [spec.column_names.index(c.name) for c in columns]
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
