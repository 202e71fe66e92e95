"""Raven-II telemetry: the u_struct codec, the listener's accounting, and `midas record` from the emulator."""

from __future__ import annotations

import json
import socket
import struct
import threading
from pathlib import Path

import pytest

from midas_cli.devices.raven.emulator import PacketSource, RavenEmulator, RavenEmulatorConfig
from midas_cli.devices.raven.protocol import (
    PACKET_SIZE, SequenceTracker, decode_packet, encode_packet, raven_checksum,
)
from midas_cli.errors import DeviceError
from midas_cli.session.device_files import read_raw_packets
from midas_cli.session.reader import Session
from tests.conftest import midas


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


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
        session, manifest = _record(tmp_path, f"raven://127.0.0.1:{port}?rate=500&forward=127.0.0.1:{robot_port}", 5)
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
