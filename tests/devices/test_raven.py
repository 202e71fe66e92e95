"""Raven-II telemetry: the u_struct codec, the listener's accounting (loopback by default, only the
console's datagrams recorded and forwarded, counts across reconnects), and `midas record` from the
emulator. Everything stays on loopback: 127.0.0.1 is the console, 127.0.0.2 a stranger."""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from midas_cli.clock import HostClock
from midas_cli.devices.base import DeviceContext, DeviceUrl
from midas_cli.devices.raven.device import RavenDevice
from midas_cli.devices.raven.emulator import PacketSource, RavenEmulator, RavenEmulatorConfig
from midas_cli.devices.raven.protocol import (
    PACKET_SIZE, SequenceTracker, decode_packet, encode_packet, raven_checksum,
)
from midas_cli.errors import ConfigError, DeviceError
from midas_cli.session.device_files import read_raw_packets
from midas_cli.session.reader import Session
from helpers.cli import midas
from helpers.net import free_udp_port



def test_layout_is_the_124_byte_u_struct_field_by_field() -> None:
    fields = [7, 1, 2, 11, -12, 21, -22, 31, -32, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 1, 2, 300, -400, 1, 0]
    data = struct.pack("<IIIiiiiiiddddddddiiiiii", *fields)
    packet = decode_packet(data)
    assert PACKET_SIZE == 124 and len(data) == 124
    assert packet.sequence == 7 and packet.delx == (11, -12) and packet.dely == (21, -22) and packet.delz == (31, -32)
    assert packet.qx == (0.1, 0.2) and packet.qw == (0.7, 0.8)
    assert packet.buttonstate == (1, 2) and packet.grasp == (300, -400) and packet.surgeon_mode == 1
    assert encode_packet(packet) == data


def test_checksum_is_the_robots_udpchecksum() -> None:
    packet = PacketSource(RavenEmulatorConfig()).block(0, 3)[2]
    expected = (packet.surgeon_mode + sum(packet.delx) + sum(packet.dely) + sum(packet.delz)
                + sum(packet.buttonstate) + packet.sequence)
    assert packet.checksum == raven_checksum(packet) == expected and packet.checksum_ok
    tampered = decode_packet(encode_packet(packet)[:-4] + struct.pack("<i", packet.checksum + 1))
    assert not tampered.checksum_ok


def test_wrong_size_datagram_is_refused() -> None:
    with pytest.raises(DeviceError, match="123 bytes, expected 124"):
        decode_packet(bytes(123))


def test_sequence_tracker_counts_gaps_duplicates_reorders_and_resets() -> None:
    tracker = SequenceTracker()
    for seq in [1, 2, 3, 6, 6, 5, 7, 5000, 5001, 10, 11]:
        tracker.update(seq)
    assert tracker.summary() == {"sequence_gaps": 2, "sequence_missing": 2 + 4992, "duplicates": 1,
                                 "out_of_order": 1, "sequence_resets": 1}


def test_emulated_surgeon_moves_plausibly() -> None:
    packets = PacketSource(RavenEmulatorConfig(rate_hz=1000)).block(0, 2000)
    assert [p.sequence for p in packets] == list(range(1, 2001))
    steps = [abs(p.delx[0]) + abs(p.dely[0]) + abs(p.delz[0]) for p in packets]
    assert 0 < max(steps) < 2000  # under 2 mm per ms: hand speeds, not jumps
    assert all(abs(p.qx[0] ** 2 + p.qy[0] ** 2 + p.qz[0] ** 2 + p.qw[0] ** 2 - 1) < 1e-9 for p in packets)
    assert len({p.grasp[1] for p in packets}) > 10


def _record(tmp_path: Path, url: str, duration: float) -> tuple[Path, dict]:
    result = midas("record", "--device", f"raven={url}", "--duration", str(duration), "--subject", "1", "--task",
                   "raven", "--trial", "1", "--out", str(tmp_path / "sessions"), "--no-tui", timeout=duration + 60)
    assert result.returncode == 0, result.stderr
    session = Path(result.stdout.strip().splitlines()[-1])
    verify = midas("session", "verify", str(session))
    assert verify.returncode == 0, verify.stdout + verify.stderr
    return session, json.loads((session / "manifest.json").read_text())


def test_record_from_the_emulator_loses_nothing_decodes_every_field_and_forwards(tmp_path: Path) -> None:
    port, robot_port = free_udp_port(), free_udp_port()
    done = threading.Event()
    robot, received = _fake_robot(robot_port, done)
    config = RavenEmulatorConfig("127.0.0.1", port, rate_hz=500, seed=3, corrupt_every=250)
    with RavenEmulator(config) as console:
        session, manifest = _record(
            tmp_path, f"raven://127.0.0.1:{port}?rate=500&from=127.0.0.1&forward=127.0.0.1:{robot_port}", 5)
    done.set()
    robot.join(timeout=5)
    frame = Session.open(session).read_stream("raven")
    assert len(frame) >= 500 * 2
    sequences = frame["sequence"].to_list()
    assert sequences == list(range(sequences[0], sequences[0] + len(sequences)))  # zero loss, in order
    assert frame["seq"].to_list() == list(range(len(frame)))
    raw = {offset: payload for offset, _, payload in read_raw_packets(session / "streams" / "raven.raw")}
    source = {p.sequence: p for p in PacketSource(config).block(0, sequences[-1])}
    for row in frame.itertuples(index=False):
        packet = decode_packet(raw[row.raw_offset])
        assert packet == source[row.sequence]  # the bytes kept are the bytes the console sent
        assert (row.arm0_delx_um, row.arm1_delz_um, row.arm1_grasp, row.surgeon_mode) == (
            packet.delx[0], packet.delz[1], packet.grasp[1], packet.surgeon_mode)
        assert row.arm0_qw == pytest.approx(packet.qw[0], abs=1e-6) and row.checksum_ok == 1
    info = manifest["devices"]["raven"]["info"]
    assert info["sequence_gaps"] == 0 and info["duplicates"] == 0 and info["packets"] == len(frame)
    wrong = len(raw) - len(frame)
    assert wrong >= 3 and info["wrong_size"] == wrong == manifest["streams"]["raven"]["corrupt"]
    assert len(received) == info["forwarded"] == len(raw)  # every datagram, the wrong-size ones too
    assert set(received) == set(raw.values()) and set(received) <= {d for _, d in console.sent} | {
        d[:-4] for _, d in console.sent}


def _fake_robot(port: int, done: threading.Event) -> tuple[threading.Thread, list[bytes]]:
    """A UDP receiver standing in for the robot; stops once ``done`` is set and nothing arrives for 0.5 s."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", port))
    sock.settimeout(0.5)
    received: list[bytes] = []

    def listen() -> None:
        with sock:
            while True:
                try:
                    received.append(sock.recv(2048))
                except socket.timeout:
                    if done.is_set():
                        return

    thread = threading.Thread(target=listen, daemon=True)
    thread.start()
    return thread, received


def _udp(host: str = "127.0.0.1") -> socket.socket:
    """A UDP socket bound to ``host`` (any free port): a sender whose address the test knows."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((host, 0))
    return sock


def _device(session_dir: Path, url: str, context: DeviceContext | None = None) -> RavenDevice:
    """A device as the worker builds it; pass one ``context`` to every reconnect of one worker."""
    context = context or DeviceContext(HostClock.anchored_now(), session_dir=str(session_dir))
    return RavenDevice("raven", DeviceUrl.parse(url), context)


def _read_until(device: RavenDevice, rows: int, timeout_s: float = 30) -> list[tuple]:
    """Rows read until ``rows`` came (datagrams on loopback arrive; the deadline only bounds a failure)."""
    got: list[tuple] = []
    deadline = time.monotonic() + timeout_s
    while len(got) < rows and time.monotonic() < deadline:
        got += device.read().get("raven", [])
    return got


def test_listen_address_is_loopback_unless_the_url_names_one() -> None:
    def address(url: str) -> tuple[str, int]:
        return RavenDevice("raven", DeviceUrl.parse(url), DeviceContext(HostClock.anchored_now())).address

    assert address("raven://") == ("127.0.0.1", 36000)
    assert address("raven://?rate=500") == ("127.0.0.1", 36000)
    assert address("raven://:36001") == ("127.0.0.1", 36001)
    assert address("raven://0.0.0.0:36000") == ("0.0.0.0", 36000)  # the robot's place on the lab network
    assert address("raven://192.168.0.5") == ("192.168.0.5", 36000)


def test_forwarding_needs_the_consoles_address() -> None:
    with pytest.raises(ConfigError, match="forward= needs from="):
        RavenDevice("raven", DeviceUrl.parse("raven://?forward=127.0.0.1:36001"), DeviceContext(HostClock.anchored_now()))
    with pytest.raises(ConfigError, match="unknown host"):
        RavenDevice("raven", DeviceUrl.parse("raven://?from=no-such-host.invalid"), DeviceContext(HostClock.anchored_now()))


def test_default_bind_takes_loopback_datagrams_only(tmp_path: Path) -> None:
    port = free_udp_port()
    device = _device(tmp_path, f"raven://:{port}")
    info = device.open()
    try:
        assert device.sock.getsockname() == ("127.0.0.1", port) and info["listen"] == f"127.0.0.1:{port}"
        packets = [encode_packet(p) for p in PacketSource(RavenEmulatorConfig()).block(0, 2)]
        with _udp("127.0.0.2") as other:
            other.sendto(packets[0], ("127.0.0.2", port))  # the same port on another address: not ours
            other.sendto(packets[1], ("127.0.0.1", port))
            rows = _read_until(device, 1)
        assert [row[2] for row in rows] == [2] and device.read() == {}
    finally:
        device.close()


def test_only_the_consoles_datagrams_are_forwarded_and_counts_survive_a_reconnect(tmp_path: Path, caplog) -> None:
    """What the worker does on a reconnect (a new device object on the same session) keeps counting."""
    robot, console, stranger, neighbour = _udp(), _udp(), _udp("127.0.0.2"), _udp()
    robot.settimeout(10)
    stranger_address = "127.0.0.2:%d" % stranger.getsockname()[1]
    port = free_udp_port()
    url = (f"raven://:{port}?from=127.0.0.1:{console.getsockname()[1]}"
           f"&forward=127.0.0.1:{robot.getsockname()[1]}")
    packets = [encode_packet(p) for p in PacketSource(RavenEmulatorConfig(seed=5)).block(0, 40)]
    foreign = [encode_packet(p) for p in PacketSource(RavenEmulatorConfig(seed=6)).block(1000, 10)]
    rows, forwarded = [], []
    caplog.set_level(logging.WARNING, logger="midas_cli")
    worker = DeviceContext(HostClock.anchored_now(), session_dir=str(tmp_path))
    for connection in range(2):
        device = _device(tmp_path, url, worker)
        device.open()
        mine = packets[20 * connection:20 * (connection + 1)]
        for k, datagram in enumerate(mine):
            if k % 4 == 0:
                stranger.sendto(foreign[k // 4], ("127.0.0.1", port))
                neighbour.sendto(foreign[k // 4 + 5], ("127.0.0.1", port))  # the console's host, another port
            console.sendto(datagram, ("127.0.0.1", port))
        console.sendto(mine[0][:100], ("127.0.0.1", port))  # a wrong-size datagram: corrupt, still forwarded
        console.sendto(mine[-1], ("127.0.0.1", port))  # a duplicate, so the last datagram is a row
        rows += _read_until(device, 21)
        forwarded += [robot.recv(2048) for _ in range(22)]
        if connection == 0:
            device.close()  # the device was lost; the worker builds a new one
    device.finish()
    device.close()
    for sock in (robot, console, stranger, neighbour):
        sock.close()
    assert [row[0] for row in rows] == list(range(42))  # seq carries on over the reconnect
    assert [decode_packet(d) for d in forwarded if len(d) == PACKET_SIZE] == [
        decode_packet(d) for d in packets[:20] + packets[19:20] + packets[20:] + packets[39:]]
    assert not set(forwarded) & set(foreign), "a stranger's datagram reached the robot"
    info = device.final_info
    assert {k: info[k] for k in ("received", "packets", "wrong_size", "foreign", "forwarded", "forward_errors",
                                 "duplicates")} == {"received": 64, "packets": 42, "wrong_size": 2, "foreign": 20,
                                                    "forwarded": 44, "forward_errors": 0, "duplicates": 2}
    assert info["first_foreign_sender"] == stranger_address
    warnings = [r for r in caplog.records if "dropping datagrams from" in r.getMessage()]
    assert len(warnings) == 1, "warned once per recording, not per datagram or per connection"


class _StatusLines:
    """`midas record --status-json`: one JSON line a second on stdout, read on a thread."""

    def __init__(self, process: subprocess.Popen) -> None:
        self.latest: dict = {}
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, args=(process.stdout,), daemon=True)
        self._thread.start()

    def _read(self, stdout) -> None:
        for line in stdout:
            if line.startswith("{"):
                with self._lock:
                    self.latest = json.loads(line)

    def wait(self, what: str, ok, timeout_s: float = 60) -> dict:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                status = self.latest
            if status and ok(status["devices"][0]):
                return status
            time.sleep(0.05)
        raise AssertionError(f"the recorder never reported {what}; last status: {self.latest}")


def test_record_keeps_only_the_consoles_datagrams_and_counts_them_over_a_reconnect(tmp_path: Path) -> None:
    """`midas record` end to end: bound to loopback by default; a stranger (127.0.0.2) and another port
    of the console's host are dropped, counted and never reach the robot; the console's datagrams are
    recorded and forwarded; a silence longer than the stall timeout forces a reconnect, and the
    manifest's counts cover both connections."""
    port = free_udp_port()
    robot_port = free_udp_port()
    done = threading.Event()
    robot, at_robot = _fake_robot(robot_port, done)
    console, stranger, neighbour = _udp(), _udp("127.0.0.2"), _udp()
    # rate=2: the stall timeout is 10 / rate = 5 s, so the phases below have 5 s to start on a busy host
    url = (f"raven://:{port}?rate=2&from=127.0.0.1:{console.getsockname()[1]}"
           f"&forward=127.0.0.1:{robot_port}")
    env = {**os.environ, "NO_COLOR": "1"}
    process = subprocess.Popen([sys.executable, "-m", "midas_cli", "record", "--device", f"raven={url}",
                                "--subject", "1", "--task", "raven", "--trial", "1", "--out",
                                str(tmp_path / "sessions"), "--status-json"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        status = _StatusLines(process)
        packets = [encode_packet(p) for p in PacketSource(RavenEmulatorConfig(seed=2)).block(0, 60)]
        strangers = [encode_packet(p) for p in PacketSource(RavenEmulatorConfig(seed=9)).block(5000, 12)]
        sent: list[bytes] = []

        def phase(mine: list[bytes], theirs: list[bytes]) -> None:
            for k, datagram in enumerate(mine):
                if k % 5 == 0:
                    stranger.sendto(theirs[k // 5], ("127.0.0.1", port))
                    neighbour.sendto(theirs[k // 5], ("127.0.0.1", port))
                    stranger.sendto(theirs[k // 5], ("127.0.0.2", port))  # not bound there: never arrives
                if k == 10:
                    console.sendto(datagram[:64], ("127.0.0.1", port))  # wrong size
                    sent.append(datagram[:64])
                console.sendto(datagram, ("127.0.0.1", port))
                sent.append(datagram)

        listening = ("ok", "degraded")  # opened ("degraded": opened, nothing received for a while)
        status.wait("the listener open", lambda d: d["state"] in listening)
        phase(packets[:30], strangers[:6])
        status.wait("30 rows", lambda d: d["streams"][0]["samples"] >= 30)
        status.wait("a reconnect after the silence", lambda d: d["reconnects"] >= 1 and d["state"] in listening)
        phase(packets[30:], strangers[6:])
        status.wait("60 rows", lambda d: d["streams"][0]["samples"] >= 60)
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
        for sock in (console, stranger, neighbour):
            sock.close()
    done.set()
    robot.join(timeout=5)
    assert process.returncode == 0, stderr
    session = tmp_path / "sessions" / os.listdir(tmp_path / "sessions")[0]
    manifest = json.loads((session / "manifest.json").read_text())
    device = manifest["devices"]["raven"]
    assert device["settings"]["listen"] == f"127.0.0.1:{port}" and device["info"]["listen"] == f"127.0.0.1:{port}"
    assert device["reconnects"] >= 1
    info = device["info"]
    assert {k: info[k] for k in ("received", "packets", "wrong_size", "foreign", "forwarded", "forward_errors")} == {
        "received": 62 + 24, "packets": 60, "wrong_size": 2, "foreign": 24, "forwarded": 62, "forward_errors": 0}
    assert manifest["streams"]["raven"]["corrupt"] == 2
    assert at_robot == sent, "the robot gets the console's datagrams, in order, and nothing else"
    frame = Session.open(session).read_stream("raven")
    assert frame["seq"].to_list() == list(range(60)) and frame["sequence"].to_list() == list(range(1, 61))
    assert stderr.count("dropping datagrams from 127.0.0.") == 1, stderr
    assert midas("session", "verify", str(session)).returncode == 0


def test_a_new_process_resumes_counting_from_the_raw_file(tmp_path: Path, caplog, monkeypatch) -> None:
    """Without the worker's tally (another process), seq, packets and wrong-size counts still continue
    from the raw file; what it cannot know (forwarded, foreign) restarts, and the log says so."""
    port = free_udp_port()
    packets = [encode_packet(p) for p in PacketSource(RavenEmulatorConfig(seed=1)).block(0, 6)]
    rows = []
    with _udp() as console:
        for connection in range(2):
            device = _device(tmp_path, f"raven://:{port}")  # a new context each time: another process
            device.open()
            console.sendto(packets[3 * connection][:10], ("127.0.0.1", port))
            for datagram in packets[3 * connection:3 * connection + 3]:
                console.sendto(datagram, ("127.0.0.1", port))
            rows += _read_until(device, 3)
            if connection:
                device.finish()
            device.close()
    assert [row[0] for row in rows] == list(range(6)) and [row[2] for row in rows] == list(range(1, 7))
    info = device.final_info
    assert (info["packets"], info["wrong_size"], info["sequence_gaps"]) == (6, 2, 0)
    assert "counting resumes from" in caplog.text
