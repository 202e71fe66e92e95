"""``raven://HOST:PORT?forward=HOST:PORT&rate=HZ``: listen for the Raven-II console's UDP packets.

The listener binds HOST:PORT (``0.0.0.0:36000`` to take the robot's place on the network; the console
must then send to this laptop, and ``forward=ROBOT:36000`` passes every datagram on unchanged, as the
original MiDAS logger did). Each datagram is stamped with the host clock when it was read, kept
byte for byte in ``streams/<name>.raw`` (see :mod:`midas_cli.session.device_files`) and, when it is a
124-byte ``u_struct``, decoded into the ``<name>`` stream. Datagrams of another size are counted as
corrupt (their bytes are still in the raw file).

``seq`` counts the packets this listener received (it never goes back, so a console restart cannot
break the stream); the console's own ``sequence`` is a column, and its gaps, duplicates, out-of-order
packets and resets are counted and written to the device's manifest info at the end.
"""

from __future__ import annotations

import logging
import select
import socket
from typing import Any

from midas_cli.clock import HostClock
from midas_cli.devices.base import Device, DeviceUrl
from midas_cli.devices.raven.protocol import PACKET_SIZE, SequenceTracker, decode_packet
from midas_cli.errors import ConfigError, DeviceError
from midas_cli.session.device_files import RawPacketWriter, raw_file_name, read_raw_packets
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec

log = logging.getLogger(__name__)

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


class RavenDevice(Device):
    """UDP listener (and optional forwarder) for Raven-II teleoperation packets."""

    kind = "raven"

    def __init__(self, name: str, url: DeviceUrl, clock: HostClock, session_dir: str = "") -> None:
        super().__init__(name, url)
        self.params = url.take({"forward": str, "rate": float}, {"forward": "", "rate": 1000.0})
        if not 0 < self.params["rate"] <= 10000:
            raise ConfigError(f"{url.raw}: rate must be in (0, 10000] Hz (the console's send rate), "
                              f"got {self.params['rate']}")
        self.address = parse_address(url.target.strip("/") or f"0.0.0.0:{DEFAULT_PORT}", f"{url.raw}: listen address",
                                     DEFAULT_PORT)
        self.forward = parse_address(self.params["forward"], f"{url.raw}: forward") if self.params["forward"] else None
        self.clock = clock
        self.session_dir = session_dir
        self.sock: socket.socket | None = None
        self.raw: RawPacketWriter | None = None
        self.tracker = SequenceTracker()
        self.received = 0
        self.forwarded = 0
        self.forward_errors = 0
        self._last_t = 0

    @property
    def streams(self) -> list[StreamSpec]:
        return [StreamSpec(self.name, self.name, COLUMNS, self.params["rate"],
                           "Raven-II teleoperation packets (u_struct), one row per 124-byte datagram")]

    def settings(self) -> dict[str, Any]:
        return {"listen": f"{self.address[0]}:{self.address[1]}", "forward": self.params["forward"] or None,
                "rate": self.params["rate"], "raw_file": raw_file_name(self.name)}

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
        self._resume(self.raw.path)
        log.info("%s: listening on udp %s:%d%s", self.name, *self.address,
                 f", forwarding to {self.forward[0]}:{self.forward[1]}" if self.forward else "")
        return {"model": "Raven-II surgeon console (ITP u_struct over UDP)", "packet_bytes": PACKET_SIZE,
                "listen": f"{self.address[0]}:{self.address[1]}", "raw_file": raw_file_name(self.name)}

    def _resume(self, raw_path) -> None:
        """After a reconnect, continue ``seq``, time order and the sequence counts from the raw file."""
        for _, t_host, payload in read_raw_packets(raw_path):
            self._last_t = t_host
            if len(payload) == PACKET_SIZE:
                self.tracker.update(decode_packet(payload).sequence)
                self.received += 1

    def read(self) -> dict[str, list[tuple]]:
        if self.sock is None or self.raw is None:
            raise DeviceError(f"{self.name}: read before open")
        ready, _, _ = select.select([self.sock], [], [], POLL_S)
        rows: list[tuple] = []
        while ready and len(rows) < MAX_PACKETS_PER_READ:
            try:
                data = self.sock.recv(MAX_DATAGRAM)
            except BlockingIOError:
                break
            row = self._take(data)
            if row is not None:
                rows.append(row)
        return {self.name: rows} if rows else {}

    def _take(self, data: bytes) -> tuple | None:
        """Stamp, keep, forward and decode one datagram; the row for the stream or None."""
        t_host = max(self.clock.now_ns(), self._last_t + 1)  # strictly increasing within the stream
        self._last_t = t_host
        offset = self.raw.append(t_host, data)
        self._forward(data)
        try:
            packet = decode_packet(data)
        except DeviceError:
            self.counters.corrupt += 1
            self.counters.discarded_bytes += len(data)
            return None
        self.tracker.update(packet.sequence)
        row = (self.received, t_host, *packet.row_values(), offset)
        self.received += 1
        return row

    def _forward(self, data: bytes) -> None:
        if self.forward is None:
            return
        try:
            self.sock.sendto(data, self.forward)
            self.forwarded += 1
        except OSError as exc:
            self.forward_errors += 1
            if self.forward_errors == 1:
                log.warning("%s: forwarding to %s:%d failed: %s", self.name, *self.forward, exc)

    def finish(self) -> dict[str, list[tuple]]:
        self.final_info = {"packets": self.received, "wrong_size": self.counters.corrupt,
                           "forwarded": self.forwarded, "forward_errors": self.forward_errors,
                           **self.tracker.summary()}
        return {}

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        if self.raw is not None:
            self.raw.close()
            self.raw = None
