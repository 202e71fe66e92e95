"""The fps:// driver against the emulator on a pty (in-process), and the emulator's faults."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from midas_cli.clock import HostClock
from midas_cli.devices.base import DeviceContext, DeviceUrl
from midas_cli.devices.fps.driver import FpsDevice
from midas_cli.devices.fps.emulator import FpsEmulator, FpsEmulatorConfig
from midas_cli.devices.pty_emulator import Faults
from midas_cli.devices.registry import create_device, describe_device
from midas_cli.errors import ConfigError, DeviceError


def _device(url: str, name: str = "fps") -> FpsDevice:
    clock = HostClock.anchored_now()
    return FpsDevice(name, DeviceUrl.parse(url), DeviceContext(clock, clock.now_ns()))


def _read_for(device: FpsDevice, seconds: float) -> list[tuple]:
    rows: list[tuple] = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        rows += device.read().get(device.name, [])
    return rows


def _read_until(device: FpsDevice, wanted: int, timeout_s: float = 30) -> list[tuple]:
    """Rows read until ``wanted`` came (a busy host may take longer than the rate says; the timeout only
    bounds a failure)."""
    rows: list[tuple] = []
    deadline = time.monotonic() + timeout_s
    while len(rows) < wanted and time.monotonic() < deadline:
        rows += device.read().get(device.name, [])
    return rows


def test_stream_layout_matches_the_simulated_board() -> None:
    real = describe_device("fps", "fps:///dev/ttyACM0?rate=250&channels=9")
    sim = describe_device("fps", "sim://fps?rate=250&channels=9")
    assert real.streams[0].columns == sim.streams[0].columns
    assert real.streams[0].nominal_rate_hz == 250.0


def test_records_every_sample_the_board_sent() -> None:
    with FpsEmulator(FpsEmulatorConfig(channels=9)) as emulator:
        device = _device(f"fps://{emulator.path}?rate=200&press_v=2.0&release_v=1.0")
        info = device.open()
        rows = _read_until(device, 150)
        device.close()
        time.sleep(0.1)
    report = emulator.summary()
    sent = {s["seq"]: s for s in report["samples"]}
    assert info["firmware"] == "1.0.0" and info["board_channels"] == 9
    assert [r[0] for r in rows] == sorted(sent)[: len(rows)] and len(rows) >= 150
    for row in rows:
        assert row[2] == sent[row[0]]["t_us"] and list(row[3:12]) == sent[row[0]]["adc"]
    assert all(b > a for a, b in zip((r[1] for r in rows), (r[1] for r in rows[1:])))
    assert report["commands"] == {"ID": 1, "RATE": 1, "START": 1, "STOP": 1}


def test_pressed_states_use_per_channel_thresholds_with_hysteresis() -> None:
    with FpsEmulator(FpsEmulatorConfig(channels=2, pedals="idle", press_counts=500)) as emulator:
        device = _device(f"fps://{emulator.path}?rate=200&channels=2&press_v=2.0,3.0&release_v=1.0,2.0")
        device.open()
        emulator.force(1, True)
        emulator.force(2, True)  # 500 counts = 2.44 V: above channel 1's 2.0 V, below channel 2's 3.0 V
        rows = _read_for(device, 0.5)
        device.close()
    assert rows[-1][5:] == (1, 0)


@pytest.mark.parametrize("seed", [4, 8])  # 4 damaged the ID reply on every resend within the default 3 s
def test_corrupted_bytes_are_counted_and_never_recorded(seed: int) -> None:
    config = FpsEmulatorConfig(channels=9, seed=seed, faults=Faults(corrupt=0.01, drop=0.002))
    with FpsEmulator(config) as emulator:
        # a noisy line can damage the ~85-byte handshake reply several times: give it time to resend
        device = _device(f"fps://{emulator.path}?rate=400&timeout=15")
        device.open()
        rows = _read_until(device, 600, timeout_s=120)  # ~360 damaged bytes expected in 600 lines
        device.close()
    report = emulator.summary()
    sent = {s["seq"]: s for s in report["samples"]}
    assert device.counters.corrupt > 0 and device.counters.discarded_bytes > 0
    assert all(list(r[3:12]) == sent[r[0]]["adc"] and r[2] == sent[r[0]]["t_us"] for r in rows)
    intact = [s["seq"] for s in report["samples"] if s["intact"] and s["seq"] <= rows[-1][0]]
    assert set(intact) <= {r[0] for r in rows}


def test_board_restart_continues_the_session_sequence(tmp_path: Path) -> None:
    link = tmp_path / "fps"
    with FpsEmulator(FpsEmulatorConfig(channels=3, link=link)) as emulator:
        clock = HostClock.anchored_now()
        start = clock.now_ns()
        worker = DeviceContext(clock, start)  # the worker keeps one context over reconnects
        first = create_device("fps", f"fps://{link}?rate=200&channels=3", worker)
        first.open()
        before = _read_for(first, 0.3)
        emulator.set_unplugged(True)
        with pytest.raises(DeviceError):
            _read_for(first, 1.0)
        first.close()
        emulator.set_unplugged(False)
        time.sleep(0.1)
        second = create_device("fps", f"fps://{link}?rate=200&channels=3", worker)
        second.open()
        after = _read_for(second, 0.3)
        second.close()
    assert len(emulator.summary()["boots"]) == 2
    assert after[0][0] > before[-1][0] and second.counters.extra["seq_rebased"] == 1


def test_silence_and_missing_ports_raise_device_errors(tmp_path: Path) -> None:
    with pytest.raises(DeviceError, match="cannot open"):
        _device(f"fps://{tmp_path}/nothing?rate=100").open()
    with FpsEmulator(FpsEmulatorConfig(faults=Faults(stall_at=0.0, stall_for=5.0))) as emulator:
        with pytest.raises(DeviceError, match="no answer to 'ID'"):
            _device(f"fps://{emulator.path}?rate=100&timeout=0.6").open()


def test_refusals_are_clear() -> None:
    with pytest.raises(ConfigError, match="rate must be 1..1000 Hz"):
        describe_device("fps", "fps:///dev/ttyACM0?rate=5000")
    with pytest.raises(ConfigError, match="press_v needs 1 or 9"):
        describe_device("fps", "fps:///dev/ttyACM0?press_v=1,2")
    with pytest.raises(ConfigError, match="unknown parameter"):
        describe_device("fps", "fps:///dev/ttyACM0?speed=3")
    with FpsEmulator(FpsEmulatorConfig(channels=4)) as emulator:
        with pytest.raises(DeviceError, match="the board has 4 channels"):
            _device(f"fps://{emulator.path}?rate=100&channels=9").open()
    with FpsEmulator(FpsEmulatorConfig(channels=9, rate_hz=200, baud=115200)) as emulator:
        with pytest.raises(DeviceError, match="at 115200 baud: at most 230 Hz"):
            _device(f"fps://{emulator.path}?rate=250&baud=115200").open()


def test_emulator_controls(tmp_path) -> None:
    with pytest.raises(ConfigError, match="unplug needs --link"):
        FpsEmulator(FpsEmulatorConfig(channels=2)).control("unplug")
    emulator = FpsEmulator(FpsEmulatorConfig(channels=2, link=str(tmp_path / "fps")))
    emulator.control("press 2")
    emulator.control("unplug")
    assert emulator._forced == [None, True] and not emulator._plug_wanted(time.monotonic())
    emulator.control("replug")
    assert emulator._plug_wanted(time.monotonic())
    with pytest.raises(ConfigError, match="unknown emulator control"):
        emulator.control("jump 3")
