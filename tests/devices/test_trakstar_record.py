"""`midas record` from the trakSTAR emulator on a pty: zero loss, 1% corruption, unplug/replug."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from midas_cli.devices.trakstar.emulator import TrakstarEmulator
from midas_cli.session.integrity import verify_session
from midas_cli.session.reader import Session
from helpers.cli import midas
from helpers.trakstar import expected_values

META = ("--subject", "1", "--task", "suturing", "--trial", "1")
SENSOR_COLUMNS = [f"s{s}_{a}" for s in range(1, 5) for a in ("x_mm", "y_mm", "z_mm", "azimuth_deg",
                                                              "elevation_deg", "roll_deg")]


def _record(out: Path, link: str, duration: float) -> subprocess.CompletedProcess:
    url = f"emht=fob://{link}?rate=200&sensors=4&baud=115200&range=36"
    return midas("record", "--device", url, "--duration", str(duration), "--out", str(out), *META, "--no-tui",
                 timeout=duration + 60)


def _check_zero_loss(emu: TrakstarEmulator, path: Path) -> None:
    summary = emu.summary()
    frame = Session.open(path).read_stream("emht")
    assert (np.diff(frame["seq"].to_numpy()) == 1).all()
    assert 0 <= summary["stream_groups_sent"] - len(frame) <= 4, "all but the cycles in flight at stop"
    expected = expected_values(emu, summary, 0, len(frame)).reshape(len(frame), 24)
    assert np.allclose(frame[SENSOR_COLUMNS].to_numpy(), expected, atol=6e-4), "values survive the CSV (3 dp)"
    assert Session.open(path).manifest["streams"]["emht"]["corrupt"] == 0


def test_record_from_the_emulator_loses_nothing_at_4_sensors_200_hz(emulator, tmp_path: Path) -> None:
    result = _record(tmp_path / "out", emulator.path, 8)
    assert result.returncode == 0, result.stderr
    path = Path(result.stdout.strip().splitlines()[-1])
    assert midas("session", "verify", str(path)).returncode == 0
    _check_zero_loss(emulator, path)
    manifest = Session.open(path).manifest
    assert manifest["devices"]["emht"]["info"]["serial"] == "4242"
    assert abs(manifest["streams"]["emht"]["measured_rate_hz"] - 200) < 2
    adapter = manifest["devices"]["emht"]["info"]["usb_serial"]  # what was in force on the port (issue 26)
    assert (adapter["adapter"], adapter["low_latency"]) == ("not usb", "unsupported")


@pytest.mark.slow
def test_record_60_s_from_the_emulator_loses_nothing(emulator, tmp_path: Path) -> None:
    result = _record(tmp_path / "out", emulator.path, 60)
    assert result.returncode == 0, result.stderr
    path = Path(result.stdout.strip().splitlines()[-1])
    assert verify_session(path).ok
    _check_zero_loss(emulator, path)


@pytest.mark.parametrize("emulator", [{"corrupt": 0.01, "seed": 5}], indirect=True)
def test_record_with_1_percent_corruption_keeps_only_clean_records(emulator, tmp_path: Path) -> None:
    result = _record(tmp_path / "out", emulator.path, 4)
    assert result.returncode == 0, result.stderr
    path = Path(result.stdout.strip().splitlines()[-1])
    assert verify_session(path).ok
    session = Session.open(path)
    frame = session.read_stream("emht")
    summary = emulator.summary()
    index = frame["seq"].to_numpy() - frame["seq"].iloc[0]
    expected = expected_values(emulator, summary, 0, int(index[-1]) + 1)[index].reshape(len(frame), 24)
    values = frame[SENSOR_COLUMNS].to_numpy()
    present = ~np.isnan(values)
    assert np.allclose(values[present], expected[present], atol=6e-4), "no corrupted value in the file"
    assert session.manifest["streams"]["emht"]["corrupt"] >= 0.9 * len(summary["damaged"]) > 50
    assert (~present).sum() // 6 <= session.manifest["streams"]["emht"]["corrupt"]


def test_unplug_and_replug_reconnects_within_2_s_and_records_the_gap(emulator, tmp_path: Path) -> None:
    url = f"emht=fob://{emulator.path}?rate=200&sensors=4"
    process = subprocess.Popen([sys.executable, "-m", "midas_cli", "record", "--device", url, "--duration", "9",
                                "--out", str(tmp_path / "out"), *META, "--no-tui"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "NO_COLOR": "1"})
    try:
        deadline = time.monotonic() + 30
        while emulator.summary()["stream_groups_sent"] < 200 and time.monotonic() < deadline:
            time.sleep(0.05)
        emulator.unplug(2.0)
        stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
    assert process.returncode == 0, stderr
    path = Path(stdout.strip().splitlines()[-1])
    manifest = Session.open(path).manifest
    replugged_ns = emulator.summary()["unplugs"][0]["replugged_ns"]
    events = manifest["devices"]["emht"]["events"]
    assert any(e["event"] == "lost" for e in events)
    reopened = [e["t_host_ns"] for e in events if e["event"] == "opened" and e["t_host_ns"] > replugged_ns]
    assert reopened and reopened[0] - replugged_ns < 2e9, "reconnected within 2 s of the device's return"
    gaps = manifest["streams"]["emht"]["seq_gaps"]
    assert gaps["count"] == 1 and 2 * 200 <= gaps["missing"] <= 5 * 200
    assert manifest["streams"]["emht"]["missing_explained"]["outage"] == gaps["missing"]
    assert verify_session(path).ok
