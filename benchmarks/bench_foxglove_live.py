"""Recording CPU with `midas record --foxglove` on, a client subscribed to every channel, against off.

Runs `python -m midas_cli record --simulate` (EmHT 4 x 240 Hz, FPS 9 ch x 250 Hz, video and HandKP
30 Hz, all simulated) for --duration seconds, alternately without and with the live server, and
measures each process's CPU over the middle of the recording (bench_record.steady_state_cpu). With the
server on, a websocket-client thread subscribes to every advertised channel and counts what arrives.

    .venv/bin/python benchmarks/bench_foxglove_live.py [--duration 20] [--repeat 2]  # -> results/foxglove_live.json
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_record import PY, steady_state_cpu  # noqa: E402
from machine import load_average, machine_info, write_result  # noqa: E402


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def subscribe_all(port: int, stop: threading.Event, counts: dict[str, int]) -> None:
    """Connect (retrying while the recorder starts), subscribe to every channel, count messages per topic."""
    import websocket

    while not stop.is_set():
        try:
            ws = websocket.create_connection(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], timeout=0.5)
            break
        except OSError:
            time.sleep(0.1)
    else:
        return
    topics: dict[int, str] = {}
    while not stop.is_set():
        try:
            opcode, data = ws.recv_data()
        except websocket.WebSocketTimeoutException:
            continue
        except websocket.WebSocketException:
            break
        if opcode == websocket.ABNF.OPCODE_TEXT and json.loads(data)["op"] == "advertise":
            channels = json.loads(data)["channels"]
            topics.update({c["id"]: c["topic"] for c in channels})
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": c["id"], "channelId": c["id"]}
                                                                      for c in channels]}))
        elif opcode == websocket.ABNF.OPCODE_BINARY and data[0] == 1:
            topic = topics[int.from_bytes(data[1:5], "little")]
            counts[topic] = counts.get(topic, 0) + 1
    ws.close()


def run(duration_s: float, live: bool) -> dict:
    """One recording; per-process steady-state CPU and, with the server on, the messages received."""
    port, counts, stop = free_port(), {}, threading.Event()
    extra = ["--foxglove-address", f"127.0.0.1:{port}"] if live else []
    client = threading.Thread(target=subscribe_all, args=(port, stop, counts), daemon=True) if live else None
    with tempfile.TemporaryDirectory(prefix="midas-bench-fox-") as tmp:
        load = load_average()
        proc = subprocess.Popen([PY, "-m", "midas_cli", "record", "--simulate", "--duration", str(duration_s),
                                 "--out", tmp, "--subject", "1", "--task", "bench", "--trial", "1", "--no-tui", *extra],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        if client is not None:
            client.start()
        steady = steady_state_cpu(proc, duration_s)
        _, stderr = proc.communicate()
        stop.set()
        if client is not None:
            client.join(timeout=5)
        if proc.returncode != 0:
            raise RuntimeError(f"midas record failed ({proc.returncode}): {stderr[-2000:]}")
    return {"foxglove": live, "duration_s": duration_s, "load_average_before_after": [load, load_average()],
            "steady_cpu_percent_of_one_core": steady, "messages_received": counts}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()
    runs = []
    for k in range(args.repeat):
        for live in (False, True):
            print(f"foxglove live: run {k + 1}, server {'on' if live else 'off'} ...", file=sys.stderr)
            runs.append(run(args.duration, live))
            print(json.dumps(runs[-1]["steady_cpu_percent_of_one_core"]), file=sys.stderr)
    write_result("foxglove_live", {"machine": machine_info(), "runs": runs})


if __name__ == "__main__":
    main()
