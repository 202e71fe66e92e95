"""``raven://[HOST][:PORT]?from=CONSOLE&forward=ROBOT:PORT&rate=HZ``: the Raven-II console's UDP packets.

The listener binds HOST:PORT, by default ``127.0.0.1:36000`` (loopback: nothing off this host can
reach it). To take the robot's place on the lab network, name the interface (``raven://0.0.0.0:36000``
or the laptop's address); the console must then send to this laptop. ``from=HOST`` or
``from=HOST:PORT`` is the console: only its datagrams are recorded and, with ``forward=ROBOT:36000``,
passed on unchanged to the robot, as the original MiDAS logger did. Datagrams from any other sender
are dropped, counted as ``foreign`` and warned about once; ``forward=`` without ``from=`` is refused
(it would relay anybody's packets to the robot). Without ``from=`` every sender is recorded.

Each accepted datagram is stamped with the host clock when it was read, kept byte for byte in
``streams/<name>.raw`` (see :mod:`midas_cli.session.device_files`) and, when it is a 124-byte
``u_struct``, decoded into the ``<name>`` stream. Datagrams of another size are counted as corrupt
(their bytes are still in the raw file).

``seq`` counts the packets this listener received (it never goes back, so a console restart cannot
break the stream); the console's own ``sequence`` is a column, and its gaps, duplicates, out-of-order
packets and resets are counted and written to the device's manifest info at the end, with the
datagrams received, foreign, wrong-size and forwarded. The worker builds a new device object at each
reconnect; these counts live in a :class:`LinkTally` kept per session and stream for the life of the
worker process, so they cover the whole recording, not the last connection.
"""

from __future__ import annotations

import logging
import os
import select
import socket
from dataclasses import dataclass, field
from typing import Any

from midas_cli.devices.base import Device, DeviceContext, DeviceUrl
from midas_cli.devices.raven.protocol import PACKET_SIZE, SequenceTracker, decode_packet
from midas_cli.errors import ConfigError, DeviceError
from midas_cli.session.device_files import RAW_MAGIC, RawPacketWriter, raw_file_name, read_raw_packets
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"  # loopback unless the URL names an interface
DEFAULT_PORT = 36000
MAX_DATAGRAM = 2048
MAX_PACKETS_PER_READ = 256
POLL_S = 0.005
RECEIVE_BUFFER_BYTES = 4 << 20


def _arm_columns(arm: int) -> list[Column]:
    where = f"arm {arm} (u_struct index {arm})"
    cols = [Column(f"arm{arm}_del{a}_um", "int", "um", frame="itp", description=f"{where} position increment {a}")
            for a in "xyz"]
    cols += [Column(f"arm{arm}_q{a}", "float", "", 6, frame="itp", description=f"{where} orientation quaternion {a}")
             for a in "xyzw"]
    cols += [Column(f"arm{arm}_buttons", "int", "bits", description=f"{where} buttonstate"),
             Column(f"arm{arm}_grasp", "int", "counts", description=f"{where} grasp: +32767 full close, -32768 open")]
    return cols


COLUMNS = (
    SEQ, T_HOST,
    Column("sequence", "int", "count", description="console's packet sequence number (u_struct.sequence)"),
    Column("pactyp", "int", "", description="protocol type in use"),
    Column("version", "int", "", description="protocol version"),
    *_arm_columns(0), *_arm_columns(1),
    Column("surgeon_mode", "int", "bool", description="1 engaged (pedal down), 0 disengaged"),
    Column("checksum", "int", "", description="u_struct.checksum as sent"),
    Column("checksum_ok", "int", "bool", description="1 if it equals the Raven's UDPChecksum"),
    Column("raw_offset", "int", "bytes", description="byte offset of this packet's record in the raw file"),
)


def parse_address(text: str, what: str, default_port: int | None = None) -> tuple[str, int]:
    """``HOST:PORT`` -> (host, port); ConfigError saying what was expected."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = text, str(default_port) if default_port is not None else ""
    try:
        number = int(port)
    except ValueError:
        raise ConfigError(f"{what} {text!r} is not HOST:PORT") from None
    if not host or not 0 <= number <= 65535:
        raise ConfigError(f"{what} {text!r} is not HOST:PORT with a port in 0..65535")
    return host, number


def listen_address(target: str, what: str) -> tuple[str, int]:
    """The URL's ``[HOST][:PORT]`` -> (host, port), loopback and port 36000 where left out."""
    target = target.strip("/")
    if target.startswith(":"):
        target = DEFAULT_HOST + target
    return parse_address(target or DEFAULT_HOST, what, DEFAULT_PORT)


def sender_address(text: str, what: str) -> tuple[str, int | None]:
    """``HOST`` or ``HOST:PORT`` -> (IPv4 address, port or None for any port); ConfigError if unknown."""
    host, port = parse_address(text, what, 0) if ":" in text else (text, 0)
    try:
        address = socket.gethostbyname(host)
    except (OSError, UnicodeError):
        raise ConfigError(f"{what} {text!r}: unknown host {host!r}") from None
    return address, port or None


@dataclass
class LinkTally:
    """What a listener counted since the recording began. Kept for the life of the worker process
    (see :func:`tally_for`), so a reconnect, which builds a new device, carries on counting.
    ``received`` = ``packets`` + ``wrong_size`` + ``foreign``."""

    raw_size: int = 0  # size of the raw file after the last packet counted here (another size: stale)
    last_t: int = 0
    packets: int = 0
    wrong_size: int = 0
    foreign: int = 0
    forwarded: int = 0
    forward_errors: int = 0
    first_foreign: str = ""
    tracker: SequenceTracker = field(default_factory=SequenceTracker)

    @property
    def received(self) -> int:
        return self.packets + self.wrong_size + self.foreign

    def resume(self, raw_path: Any) -> None:
        """Count what an earlier connection kept in the raw file (``seq``, time order, sequences)."""
        for _, t_host, payload in read_raw_packets(raw_path):
            self.last_t = t_host
            if len(payload) == PACKET_SIZE:
                self.tracker.update(decode_packet(payload).sequence)
                self.packets += 1
            else:
                self.wrong_size += 1

    def info(self) -> dict[str, Any]:
        info = {"received": self.received, "packets": self.packets, "wrong_size": self.wrong_size,
                "foreign": self.foreign, "forwarded": self.forwarded, "forward_errors": self.forward_errors,
                **self.tracker.summary()}
        if self.first_foreign:
            info["first_foreign_sender"] = self.first_foreign
        return info


def tally_for(context: DeviceContext, stream: str, raw: RawPacketWriter) -> LinkTally:
    """The running tally of ``stream`` in this session; a new one (counting what the raw file already
    holds) unless this worker's context has counted up to exactly the raw file's current end."""
    tallies: dict[tuple[str, str], LinkTally] = context.carry("raven/tallies", dict)
    key = (os.path.realpath(context.session_dir), stream)
    tally = tallies.get(key)
    if tally is None or tally.raw_size != raw.size:
        if tally is not None or raw.size > len(RAW_MAGIC):
            log.warning("%s: counting resumes from %s; datagrams forwarded or foreign before are not known",
                        stream, raw.path)
        tally = tallies[key] = LinkTally(raw_size=raw.size)
        tally.resume(raw.path)
    return tally


class RavenDevice(Device):
    """UDP listener (and optional forwarder) for Raven-II teleoperation packets."""

    kind = "raven"

    def __init__(self, name: str, url: DeviceUrl, context: DeviceContext) -> None:
        super().__init__(name, url)
        self.params = url.take({"forward": str, "from": str, "rate": float},
                               {"forward": "", "from": "", "rate": 1000.0})
        if not 0 < self.params["rate"] <= 10000:
            raise ConfigError(f"{url.raw}: rate must be in (0, 10000] Hz (the console's send rate), "
                              f"got {self.params['rate']}")
        self.address = listen_address(url.target, f"{url.raw}: listen address")
        self.forward = parse_address(self.params["forward"], f"{url.raw}: forward") if self.params["forward"] else None
        self.sender = sender_address(self.params["from"], f"{url.raw}: from") if self.params["from"] else None
        if self.forward is not None and self.sender is None:
            raise ConfigError(f"{url.raw}: forward= needs from=HOST[:PORT], the surgeon console's address: only "
                              f"its datagrams are passed on to the robot (anyone else's would reach it too)")
        self.context = context
        self.clock = context.clock
        self.session_dir = context.session_dir
        self.sock: socket.socket | None = None
        self.raw: RawPacketWriter | None = None
        self.tally = LinkTally()  # replaced by the session's running tally on open

    @property
    def streams(self) -> list[StreamSpec]:
        return [StreamSpec(self.name, self.name, COLUMNS, self.params["rate"],
                           "Raven-II teleoperation packets (u_struct), one row per 124-byte datagram")]

    def _sender_text(self) -> str | None:
        if self.sender is None:
            return None
        host, port = self.sender
        return host if port is None else f"{host}:{port}"

    def settings(self) -> dict[str, Any]:
        return {"listen": f"{self.address[0]}:{self.address[1]}", "from": self._sender_text(),
                "forward": self.params["forward"] or None, "rate": self.params["rate"],
                "raw_file": raw_file_name(self.name)}

    def open(self) -> dict[str, Any]:
        if not self.session_dir:
            raise DeviceError(f"{self.name}: raven:// keeps raw packets in a session folder; "
                              f"use it through `midas record`")
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
        try:
            sock.bind(self.address)
        except OSError as exc:
            sock.close()
            raise DeviceError(f"{self.name}: cannot listen on UDP {self.address[0]}:{self.address[1]}: {exc.strerror} "
                              f"(another program, e.g. the robot software, may hold the port)") from None
        sock.setblocking(False)
        self.sock = sock
        self.raw = RawPacketWriter(self.session_dir, self.name)
        self.tally = tally_for(self.context, self.name, self.raw)
        bound = "%s:%d" % sock.getsockname()
        log.info("%s: listening on udp %s%s%s", self.name, bound,
                 f", accepting only {self._sender_text()}" if self.sender else "",
                 f", forwarding to {self.forward[0]}:{self.forward[1]}" if self.forward else "")
        return {"model": "Raven-II surgeon console (ITP u_struct over UDP)", "packet_bytes": PACKET_SIZE,
                "listen": bound, "from": self._sender_text(), "raw_file": raw_file_name(self.name)}

    def read(self) -> dict[str, list[tuple]]:
        if self.sock is None or self.raw is None:
            raise DeviceError(f"{self.name}: read before open")
        ready, _, _ = select.select([self.sock], [], [], POLL_S)
        rows: list[tuple] = []
        for _ in range(MAX_PACKETS_PER_READ if ready else 0):
            try:
                data, source = self.sock.recvfrom(MAX_DATAGRAM)
            except BlockingIOError:
                break
            if not self._accepts(source):
                continue
            row = self._take(data)
            if row is not None:
                rows.append(row)
        return {self.name: rows} if rows else {}

    def _accepts(self, source: tuple[str, int]) -> bool:
        """Whether a datagram from ``source`` is the console's; count (and warn once about) the others."""
        if self.sender is None or (source[0] == self.sender[0] and self.sender[1] in (None, source[1])):
            return True
        self.tally.foreign += 1
        if not self.tally.first_foreign:
            self.tally.first_foreign = f"{source[0]}:{source[1]}"
            log.warning("%s: dropping datagrams from %s: only the console at %s is %s (from=); counted as "
                        "'foreign' in the manifest", self.name, self.tally.first_foreign, self._sender_text(),
                        "recorded and forwarded" if self.forward else "recorded")
        return False

    def _take(self, data: bytes) -> tuple | None:
        """Stamp, keep, forward and decode one datagram; the row for the stream or None."""
        tally = self.tally
        t_host = max(self.clock.now_ns(), tally.last_t + 1)  # strictly increasing within the stream
        tally.last_t = t_host
        offset = self.raw.append(t_host, data)
        tally.raw_size = self.raw.size
        self._forward(data)
        try:
            packet = decode_packet(data)
        except DeviceError:
            tally.wrong_size += 1
            self.counters.corrupt += 1  # this connection's; the worker adds up the connections
            self.counters.discarded_bytes += len(data)
            return None
        tally.tracker.update(packet.sequence)
        row = (tally.packets, t_host, *packet.row_values(), offset)
        tally.packets += 1
        return row

    def _forward(self, data: bytes) -> None:
        if self.forward is None:
            return
        try:
            self.sock.sendto(data, self.forward)
            self.tally.forwarded += 1
        except OSError as exc:
            self.tally.forward_errors += 1
            if self.tally.forward_errors == 1:
                log.warning("%s: forwarding to %s:%d failed: %s", self.name, *self.forward, exc)

    def finish(self) -> dict[str, list[tuple]]:
        self.final_info = self.tally.info()
        return {}

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        if self.raw is not None:
            self.raw.close()
            self.raw = None
