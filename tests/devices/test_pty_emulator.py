"""The pty emulator base: one fault vocabulary, thread errors re-raised, the host's sensor count honoured."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from midas_cli.clock import HostClock
from midas_cli.devices.base import DeviceContext, DeviceUrl
from midas_cli.devices.fps.emulator import FpsEmulator, FpsEmulatorConfig
from midas_cli.devices.pty_emulator import Faults
from midas_cli.devices.trakstar.driver import FobEmHT
from midas_cli.devices.trakstar.emulator import EmulatorConfig, TrakstarEmulator
from midas_cli.errors import ConfigError, DeviceError


def _broken(*_args) -> None:
    raise RuntimeError("emulated firmware crash")


def test_faults_are_validated_in_one_place() -> None:
    with pytest.raises(ConfigError, match="corrupt must be a probability"):
        Faults(corrupt=1.5)
    with pytest.raises(ConfigError, match="stall_for must be >= 0"):
        Faults(stall_at=1.0, stall_for=-1.0)
    with pytest.raises(ConfigError, match="give a link path"):  # the same rule for every emulator
        FpsEmulator(FpsEmulatorConfig(faults=Faults(unplug_at=1.0, unplug_for=1.0)))
    with pytest.raises(ConfigError, match="give a link path"):
        TrakstarEmulator(EmulatorConfig(faults=Faults(unplug_at=1.0, unplug_for=1.0)))


def test_a_trakstar_thread_error_is_re_raised_by_serve_for_once() -> None:
    emulator = TrakstarEmulator(EmulatorConfig())
    emulator._step = _broken
    with pytest.raises(DeviceError, match="trakSTAR emulator failed.*emulated firmware crash") as caught:
        emulator.serve_for(5.0)
    assert isinstance(caught.value.__cause__, RuntimeError)
    assert emulator.stop()["stream_groups_sent"] == 0  # already reported: stop still cleans up and summarises


def test_an_fps_thread_error_is_re_raised_by_join_and_stop() -> None:
    emulator = FpsEmulator(FpsEmulatorConfig(channels=2))
    emulator._step = _broken
    emulator.start()
    with pytest.raises(DeviceError, match="FPS emulator failed"):
        emulator.join(timeout=5.0)
    emulator.stop()  # reported once
    other = FpsEmulator(FpsEmulatorConfig(channels=2))
    other._step = _broken
    with pytest.raises(DeviceError, match="FPS emulator failed"):
        with other:
            time.sleep(0.2)


def test_the_trakstar_streams_only_the_sensors_the_host_configured(tmp_path: Path) -> None:
    emulator = TrakstarEmulator(EmulatorConfig(sensors=4, link=str(tmp_path / "trakstar"))).start()
    clock = HostClock.anchored_now()
    device = FobEmHT("emht", DeviceUrl.parse(f"fob://{emulator.path}?rate=200&sensors=2"), DeviceContext(clock, clock.now_ns()))
    try:
        device.open()
        rows: list[tuple] = []
        deadline = time.monotonic() + 30
        while len(rows) < 100 and time.monotonic() < deadline:
            rows += device.read().get("emht", [])
        device.close()
    finally:
        summary = emulator.stop()
    assert summary["sensors"] == 2 and summary["commands"]["change_50"] == 1
    assert summary["records_per_sensor"][2:] == [0, 0] and summary["records_per_sensor"][0] > 100
    assert len(rows) >= 100 and device.counters.corrupt == 0
    assert all(len(r) == 3 + 2 * 7 and None not in r[3:5] for r in rows)


def test_asking_for_more_sensors_than_are_attached_is_refused_at_open(tmp_path: Path) -> None:
    """The tracker keeps its own count when asked for more than it has; the driver reads the count back
    and refuses, instead of recording the missing sensors' empty fields as corruption."""
    emulator = TrakstarEmulator(EmulatorConfig(sensors=2, link=str(tmp_path / "trakstar"))).start()
    clock = HostClock.anchored_now()
    device = FobEmHT("emht", DeviceUrl.parse(f"fob://{emulator.path}?rate=200&sensors=4"), DeviceContext(clock, clock.now_ns()))
    try:
        with pytest.raises(DeviceError, match="runs 2 sensor"):
            device.open()
    finally:
        device.close()
        emulator.stop()
