"""`midas record` from the FPS emulator on a pty: zero loss, corruption, unplug and replug."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest

from midas_cli.devices.fps.emulator import FpsEmulator, FpsEmulatorConfig
from midas_cli.devices.pty_emulator import Faults
from midas_cli.session.reader import Session
from helpers.cli import midas


def _record(tmp_path: Path, url: str, duration: float) -> tuple[Path, dict]:
    result = midas("record", "--device", f"fps={url}", "--duration", str(duration), "--subject", "1", "--task",
                   "pedals", "--trial", "1", "--out", str(tmp_path / "sessions"), "--no-tui", timeout=duration + 60)
    assert result.returncode == 0, result.stderr
    session = Path(result.stdout.strip().splitlines()[-1])
    verify = midas("session", "verify", str(session))
    assert verify.returncode == 0, verify.stdout + verify.stderr
    return session, json.loads((session / "manifest.json").read_text())


def _rows(session: Path) -> list[tuple]:
    frame = Session.open(session).read_stream("fps")
    return list(frame.itertuples(index=False, name=None))


def _outages(manifest: dict, rows: list[tuple]) -> set[int]:
    """Sequence numbers the recorder could not see because it was reconnecting: between the last row
    before each 'lost' and the first row after the next 'opened' (on a busy host the emulator's thread
    can stall past the stall timeout; the recorder then reconnects and explains the gap as an outage)."""
    events = manifest["devices"]["fps"]["events"]
    missed: set[int] = set()
    for lost, opened in zip(events, events[1:]):
        if lost["event"] == "lost" and opened["event"] == "opened":
            before = max(r[0] for r in rows if r[1] < lost["t_host_ns"])
            after = min(r[0] for r in rows if r[1] > opened["t_host_ns"])
            missed.update(range(before + 1, after))
    return missed


@pytest.mark.parametrize("duration", [8, pytest.param(60, marks=pytest.mark.slow)])
def test_record_loses_nothing_the_board_sent(tmp_path: Path, duration: float) -> None:
    with FpsEmulator(FpsEmulatorConfig(channels=9)) as emulator:
        session, manifest = _record(tmp_path, f"fps://{emulator.path}?rate=200", duration)
    rows = _rows(session)
    outage = _outages(manifest, rows)  # none on a quiet host; a busy one may stall the emulator's thread
    sent = [s for s in emulator.summary()["samples"] if s["seq"] not in outage]
    assert len(rows) >= 200  # at least a second (the devices' start-up is part of --duration)
    assert [r[0] for r in rows] == [s["seq"] for s in sent[: len(rows)]]  # a prefix: nothing lost or reordered
    assert all(r[2] == s["t_us"] and list(r[3:12]) == s["adc"] for r, s in zip(rows, sent))
    entry = manifest["streams"]["fps"]
    assert entry["corrupt"] == 0 and entry["seq_gaps"]["missing"] == len(outage)
    assert entry["missing_explained"]["outage"] == len(outage)
    assert manifest["devices"]["fps"]["info"]["firmware"] == "1.0.0"
    adapter = manifest["devices"]["fps"]["info"]["usb_serial"]  # what was in force on the port (issue 26)
    assert adapter["note"] == "not a USB serial adapter (a pseudo-terminal)" and adapter["low_latency"] == "unsupported"


def test_one_percent_corruption_completes_counts_and_keeps_bad_values_out(tmp_path: Path) -> None:
    with FpsEmulator(FpsEmulatorConfig(channels=9, seed=7, faults=Faults(corrupt=0.01))) as emulator:
        session, manifest = _record(tmp_path, f"fps://{emulator.path}?rate=200", 6)
    sent = {s["seq"]: s for s in emulator.summary()["samples"]}
    rows = _rows(session)
    assert all(r[2] == sent[r[0]]["t_us"] and list(r[3:12]) == sent[r[0]]["adc"] for r in rows)
    outage = _outages(manifest, rows)
    assert len(outage) == manifest["streams"]["fps"]["missing_explained"]["outage"]
    decodable = {seq for seq, s in sent.items() if s["intact"] and seq <= rows[-1][0]} - outage
    assert decodable <= {r[0] for r in rows}
    lost = len([s for s in sent if s <= rows[-1][0]]) - len(rows) - len(outage)
    corrupt = manifest["streams"]["fps"]["corrupt"]
    assert lost > 0 and 0.8 * lost <= corrupt <= 1.2 * lost  # one bad line per lost sample, give or take merges


def test_unplug_and_replug_reconnects_within_two_seconds(tmp_path: Path) -> None:
    link = tmp_path / "fps-port"
    with FpsEmulator(FpsEmulatorConfig(channels=9, link=link)) as emulator:
        def pull_the_cable() -> None:
            while emulator.summary()["sent"] < 300:  # recording for about 1.5 s
                time.sleep(0.05)
            emulator.set_unplugged(True)
            time.sleep(1.0)
            emulator.set_unplugged(False)

        cable = threading.Thread(target=pull_the_cable, daemon=True)
        cable.start()
        session, manifest = _record(tmp_path, f"fps://{link}?rate=200", 8)
        cable.join(timeout=1)
    boots = emulator.summary()["boots"]
    assert len(boots) == 2
    rows = _rows(session)
    after = [r for r in rows if r[1] > boots[1]["t_host_ns"]]
    assert after and (after[0][1] - boots[1]["t_host_ns"]) / 1e9 < 2.0
    assert manifest["devices"]["fps"]["reconnects"] == 1
    assert {e["event"] for e in manifest["devices"]["fps"]["events"]} >= {"opened", "lost"}
    entry = manifest["streams"]["fps"]
    assert entry["seq_gaps"]["count"] >= 1 and entry["seq_gaps"]["resets"] == 0
    assert entry["missing_explained"]["outage"] > 0
