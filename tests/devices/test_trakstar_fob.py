"""The fob:// driver against the trakSTAR emulator on a pty, in-process and through `midas record`."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from midas_cli.clock import HostClock
from midas_cli.devices.base import DeviceContext, DeviceUrl
from midas_cli.devices.registry import describe_device
from midas_cli.devices.trakstar.driver import FobEmHT
from midas_cli.errors import ConfigError, DeviceError
from helpers.trakstar import expected_values


def _read_for(device: FobEmHT, seconds: float, wanted: int | None = None) -> list[tuple]:
    """Rows read for ``seconds``; with ``wanted``, until that many came (up to 30 s: a busy host may be
    slower than the rate says)."""
    rows: list[tuple] = []
    deadline = time.monotonic() + (seconds if wanted is None else 30)
    while time.monotonic() < deadline and (wanted is None or len(rows) < wanted):
        rows += device.read().get("emht", [])
    return rows


def _sensor_values(rows: list[tuple]) -> np.ndarray:
    """(N, 4, 6) float values of driver rows, NaN where empty."""
    table = np.array([[np.nan if v is None else v for v in r[3:]] for r in rows], dtype=float)
    return table.reshape(len(rows), 4, 7)[:, :, :6]


def test_driver_configures_the_tracker_and_decodes_every_cycle(emulator) -> None:
    clock = HostClock.anchored_now()
    device = FobEmHT("emht", DeviceUrl.parse(f"fob://{emulator.path}?rate=200&sensors=4"), DeviceContext(clock, clock.now_ns()))
    info = device.open()
    rows = _read_for(device, 2.0, wanted=350)
    device.close()
    summary = emulator.summary()
    assert info["serial"] == "4242" and info["measurement_rate_hz"] == 200.0
    assert summary["rate_hz"] == 200.0 and summary["commands"]["change_35"] == 1, "group mode set"
    assert summary["commands"]["position_angles"] == 4
    seq = np.array([r[0] for r in rows])
    assert (np.diff(seq) == 1).all() and len(rows) >= 350
    assert summary["stream_groups_sent"] - len(rows) <= 2, "only the cycles in flight at close are unread"
    assert np.array_equal(_sensor_values(rows), expected_values(emulator, summary, 0, len(rows)))
    assert all(r[2] is None and r[9] is None for r in rows), "no device clock, no quality in FOB records"
    assert device.counters.corrupt == 0 and device.counters.discarded_bytes == 0


@pytest.mark.parametrize("emulator", [{"corrupt": 0.01, "drop": 0.005, "seed": 3}], indirect=True)
def test_corrupted_and_lost_bytes_never_reach_the_rows(emulator) -> None:
    clock = HostClock.anchored_now()
    device = FobEmHT("emht", DeviceUrl.parse(f"fob://{emulator.path}?rate=200"), DeviceContext(clock, clock.now_ns()))
    device.open()
    rows = _read_for(device, 3.0)
    device.close()
    summary = emulator.summary()
    damaged = {tuple(d) for d in summary["damaged"]}
    counters = np.array(summary["stream_counters"])
    index = np.array([r[0] for r in rows]) - rows[0][0]
    values = _sensor_values(rows)
    expected = expected_values(emulator, summary, 0, int(index[-1]) + 1)[index]
    present = ~np.isnan(values[:, :, 0])
    assert np.array_equal(values[present], expected[present]), "every value that reached a row is exact"
    for row, sensor in zip(*np.nonzero(present)):
        assert (counters[index[row]], sensor + 1) not in damaged
    assert len(damaged) > 100 and (~present).sum() >= 0.9 * len(damaged)
    assert device.counters.corrupt == (~present).sum() + 4 * (index[-1] + 1 - len(rows))
    assert device.counters.discarded_bytes >= 12 * len(damaged)


def test_capacity_warning_when_the_rate_exceeds_the_line(caplog) -> None:
    device = describe_device("emht", "fob:///dev/ttyUSB0?baud=115200&sensors=4&rate=250")
    assert "221.5 records/s per sensor" in device.settings()["warning"]
    assert "221.5" in caplog.text
    assert "warning" not in describe_device("emht", "fob:///dev/ttyUSB0?sensors=4&rate=200").settings()


@pytest.mark.parametrize("url, message", [("fob://?rate=100", "no serial port"),
                                          ("fob:///dev/x?range=48", "36 or 72"),
                                          ("fob:///dev/x?baud=1234", "baud must be"),
                                          ("fob:///dev/x?rate=300", "rate must be"),
                                          ("fob:///dev/x?parity=odd", "unknown parameter")])
def test_bad_urls_are_refused(url: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        describe_device("emht", url)


def test_missing_port_and_silent_device_raise_device_errors(tmp_path: Path) -> None:
    clock = HostClock.anchored_now()
    with pytest.raises(DeviceError, match="cannot open serial port"):
        FobEmHT("emht", DeviceUrl.parse(f"fob://{tmp_path}/nothing"), DeviceContext(clock, 0)).open()
    master, slave = os.openpty()  # a port nobody answers on
    try:
        with pytest.raises(DeviceError, match="no answer to EXAMINE"):
            FobEmHT("emht", DeviceUrl.parse(f"fob://{os.ttyname(slave)}"), DeviceContext(clock, 0)).open()
    finally:
        os.close(master)
        os.close(slave)


def test_stall_makes_the_driver_report_silence(emulator) -> None:
    clock = HostClock.anchored_now()
    device = FobEmHT("emht", DeviceUrl.parse(f"fob://{emulator.path}?rate=100&timeout=0.3"), DeviceContext(clock, clock.now_ns()))
    device.open()
    assert _read_for(device, 0.3)
    emulator.stall(2.0)
    with pytest.raises(DeviceError, match="no data"):
        _read_for(device, 1.5)
    device.close()
    assert emulator.summary()["cycles_skipped_stall"] > 0


def test_emulate_command_serves_a_pty_and_writes_its_summary(tmp_path: Path) -> None:
    link, summary = tmp_path / "trakstar", tmp_path / "sent.json"
    process = subprocess.Popen([sys.executable, "-m", "midas_cli", "emulate", "trakstar", "--link", str(link),
                                "--summary", str(summary)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    try:
        assert process.stdout.readline().strip() == str(link)
        clock = HostClock.anchored_now()
        device = FobEmHT("emht", DeviceUrl.parse(f"fob://{link}?rate=100&sensors=4"), DeviceContext(clock, clock.now_ns()))
        device.open()
        rows = _read_for(device, 1.0, wanted=51)
        device.close()
    finally:
        process.send_signal(signal.SIGTERM)
        process.communicate(timeout=10)
    assert process.returncode == 0
    sent = json.loads(summary.read_text())
    assert sent["rate_hz"] == 100.0 and 0 <= sent["stream_groups_sent"] - len(rows) <= 2 and len(rows) > 50
    streamed, points = sent["stream_groups_sent"], sent["commands"]["point"]
    assert sent["records_per_sensor"] == [streamed + points] + [streamed + points - 1] * 3, \
        "the first POINT (stopping a stream) came before group mode: sensor 1 only"
    assert not link.exists(), "the link is removed at exit"


def test_a_late_point_answer_is_drained_not_read_as_the_settings(tmp_path: Path) -> None:
    """On a busy host (or behind a USB-serial adapter's latency timer) the answer to the POINT that stops
    a stream left running came after the driver's fixed 50 ms wait and was read as the EXAMINE answers:
    'measurement rate 20.66 Hz, position scaling 31313, group mode 112' and the recording failed."""
    from midas_cli.devices.trakstar.emulator import EmulatorConfig, TrakstarEmulator

    emu = TrakstarEmulator(EmulatorConfig(link=str(tmp_path / "trakstar"), point_delay_s=0.2)).start()
    try:
        clock = HostClock.anchored_now()
        device = FobEmHT("emht", DeviceUrl.parse(f"fob://{emu.path}?rate=100&sensors=4"),
                         DeviceContext(clock, clock.now_ns()))
        info = device.open()
        rows = _read_for(device, 1.0, wanted=20)
        device.close()
    finally:
        emu.stop()
    assert info["measurement_rate_hz"] == 100.0 and len(rows) >= 20
    assert (np.diff([r[0] for r in rows]) == 1).all()
