"""`midas record --foxglove`: a WebSocket client (websocket-client, speaking the Foxglove WebSocket
protocol by hand) subscribes to every advertised channel and receives messages of every stream."""

from __future__ import annotations

import json
import socket
import struct
import time
from pathlib import Path

import pytest

from midas_cli.record.foxglove_live import parse_address
from midas_cli.errors import ConfigError
from helpers.cli import midas, record_until

META = ["--subject", "1", "--task", "suturing", "--trial", "1"]
SUBPROTOCOL = "foxglove.sdk.v1"  # foxglove-sdk's name for foxglove.websocket.v1 (the same messages)
MESSAGE_DATA = 0x01


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class LiveClient:
    """Connects once the server is up, subscribes to every channel it advertises, counts what comes."""

    def __init__(self, port: int, control: Path, marker: str) -> None:
        self.port, self.control, self.marker = port, control, marker
        self.ws = None
        self.channels: dict[int, dict] = {}  # channel id -> advertised channel
        self.received: dict[str, list[tuple[int, bytes]]] = {}  # topic -> (timestamp ns, payload)
        self.server_info: dict | None = None
        self.marked = False

    def __call__(self, out: Path) -> bool:
        """``record_until``'s ``until``: True once every stream, the marker's too, has arrived."""
        if self.ws is None:
            self._connect()
            return False
        self._pump(0.5)
        topics = {c["topic"] for c in self.channels.values()}
        waiting = topics - set(self.received)
        if waiting == {"/events"} and not self.marked:
            midas("mark", self.marker, "--control", str(self.control), check=True)
            self.marked = True
        return bool(topics) and not waiting

    def _connect(self) -> None:
        import websocket

        try:
            self.ws = websocket.create_connection(f"ws://127.0.0.1:{self.port}", subprotocols=[SUBPROTOCOL], timeout=1)
        except OSError:
            self.ws = None  # not listening yet: the recorder is starting

    def _pump(self, seconds: float) -> None:
        import websocket

        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                opcode, data = self.ws.recv_data()
            except websocket.WebSocketTimeoutException:
                return
            if opcode == websocket.ABNF.OPCODE_TEXT:
                self._on_json(json.loads(data))
            elif opcode == websocket.ABNF.OPCODE_BINARY and data[0] == MESSAGE_DATA:
                subscription, stamp = struct.unpack_from("<IQ", data, 1)
                topic = self.channels[subscription]["topic"]  # subscription id = channel id
                self.received.setdefault(topic, []).append((stamp, bytes(data[13:])))

    def _on_json(self, message: dict) -> None:
        if message["op"] == "serverInfo":
            self.server_info = message
        elif message["op"] == "advertise":
            new = [c for c in message["channels"] if c["id"] not in self.channels]
            self.channels.update({c["id"]: c for c in new})
            self.ws.send(json.dumps({"op": "subscribe",
                                     "subscriptions": [{"id": c["id"], "channelId": c["id"]} for c in new]}))

    def close(self) -> None:
        if self.ws is not None:
            self.ws.close()


def test_live_streams_reach_a_websocket_client(tmp_path: Path) -> None:
    port, control = _free_port(), tmp_path / "record.sock"
    client = LiveClient(port, control, "needle in")
    try:
        result = record_until(tmp_path / "out", ["--simulate", *META, "--no-tui", "--control", str(control),
                                                 "--foxglove-address", f"127.0.0.1:{port}"], until=client, timeout=120)
    finally:
        client.close()
    assert result.returncode == 0, result.stderr
    assert f"serving ws://127.0.0.1:{port}" in result.stderr
    streams = {"emht", "fps", "video", "handkp", "events"}
    topics = {c["topic"]: c for c in client.channels.values()}
    assert set(topics) == {f"/{s}" for s in streams} | {"/emht/transforms"}
    assert set(client.received) == set(topics)  # messages of every stream
    assert topics["/emht/transforms"]["schemaName"] == "foxglove.FrameTransforms"
    assert topics["/emht/transforms"]["encoding"] == "protobuf"
    assert topics["/events"]["schemaName"] == "foxglove.Log"
    for name in ("emht", "fps", "video", "handkp"):
        schema = json.loads(topics[f"/{name}"]["schema"])
        assert all(isinstance(p["type"], str) for p in schema["properties"].values())
        for stamp, payload in client.received[f"/{name}"]:
            row = json.loads(payload)
            assert row["t_host_ns"] == stamp and set(row) <= set(schema["properties"])
        seqs = [json.loads(p)["seq"] for _, p in client.received[f"/{name}"]]
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)  # the recorded rows, in order
    assert b"needle in" in client.received["/events"][0][1]  # the marker's text in its foxglove.Log


def test_a_port_in_use_is_refused_before_anything_is_recorded(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = midas("record", "--simulate", *META, "--duration", "1", "--no-tui", "--out", str(tmp_path / "out"),
                       "--foxglove", "--foxglove-address", f"127.0.0.1:{port}")
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert str(port) in result.stderr and not any((tmp_path / "out").glob("*/manifest.json"))


@pytest.mark.parametrize(("text", "expected"), [("127.0.0.1:9000", ("127.0.0.1", 9000)), (":9001", ("127.0.0.1", 9001)),
                                                ("0.0.0.0", ("0.0.0.0", 8765)), ("[::1]:9002", ("::1", 9002))])
def test_addresses(text: str, expected: tuple[str, int]) -> None:
    assert parse_address(text) == expected


@pytest.mark.parametrize("text", ["host:http", "host:0", "host:70000"])
def test_bad_addresses_are_refused(text: str) -> None:
    with pytest.raises(ConfigError):
        parse_address(text)
