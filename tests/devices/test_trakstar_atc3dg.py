"""The atc3dg:// backend against a fake ATC3DG shared library compiled with gcc at test time."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from midas_cli.clock import HostClock
from midas_cli.devices.base import DeviceContext, DeviceUrl
from midas_cli.devices.registry import create_device
from midas_cli.devices.trakstar.atc3dg import LIB_ENV, Atc3dgEmHT
from midas_cli.errors import ConfigError, DeviceError

SOURCE = Path(__file__).parent / "fake_atc3dg" / "fake_atc3dg.c"


@pytest.fixture(scope="module")
def fake_lib(tmp_path_factory) -> Path:
    if shutil.which("gcc") is None:
        pytest.skip("gcc is not installed: cannot build the fake ATC3DG library")
    lib = tmp_path_factory.mktemp("atc3dg") / "libfake_atc3dg.so"
    subprocess.run(["gcc", "-shared", "-fPIC", "-O1", "-o", str(lib), str(SOURCE)], check=True)
    return lib


def _device(url: str) -> Atc3dgEmHT:
    clock = HostClock.anchored_now()
    device = create_device("emht", url, DeviceContext(clock, clock.now_ns()))
    assert isinstance(device, Atc3dgEmHT)
    return device


def _rows(device: Atc3dgEmHT, count: int) -> list[tuple]:
    return [device.read()["emht"][0] for _ in range(count)]


def test_records_are_decoded_in_the_emht_layout(fake_lib: Path) -> None:
    device = _device(f"atc3dg://?lib={fake_lib}&rate=200&range=72&metric=1")
    info = device.open()
    try:
        rows = _rows(device, 12)
    finally:
        device.close()
    assert info["measurement_rate_hz"] == 200.0 and info["maximum_range_in"] == 72.0
    assert info["serial"] == "9000,9001,9002,9003"
    names = device.streams[0].column_names
    first, second = dict(zip(names, rows[0])), dict(zip(names, rows[1]))
    assert first["s1_x_mm"] == 100.0 and first["s2_x_mm"] == 110.0 and second["s1_x_mm"] == 100.5
    assert first["s4_azimuth_deg"] == 3.0 and first["s4_elevation_deg"] == -3.0 and first["s4_quality"] == 3.0
    assert first["t_device_s"] == 1000.0 and second["t_device_s"] == pytest.approx(1000.005)
    assert first["s3_x_mm"] is None and second["s3_x_mm"] == 120.5, "sensor 3 not attached in cycle 0"
    assert device.counters.corrupt == 2  # cycles 0 and 10
    assert [r[0] for r in rows] == list(range(rows[0][0], rows[0][0] + 12))
    assert len(rows[0]) == len(names)


def test_inches_are_converted_to_mm(fake_lib: Path, monkeypatch) -> None:
    monkeypatch.setenv(LIB_ENV, str(fake_lib))
    device = _device("atc3dg://?rate=100&metric=0")
    device.open()
    try:
        row = dict(zip(device.streams[0].column_names, _rows(device, 1)[0]))
    finally:
        device.close()
    assert row["s2_x_mm"] == pytest.approx(110.0) and row["s1_z_mm"] == pytest.approx(150.0)


def test_missing_library_and_missing_daemon_are_clear_device_errors(fake_lib: Path, tmp_path: Path,
                                                                    monkeypatch) -> None:
    with pytest.raises(DeviceError, match="cannot load the ATC3DG library.*MIDAS_ATC3DG_LIB"):
        _device(f"atc3dg://?lib={tmp_path}/libATC3DG.so").open()
    monkeypatch.setenv("FAKE_ATC3DG_NO_DAEMON", "1")
    with pytest.raises(DeviceError, match="InitializeBIRDSystem failed: couldn't start driver.*daemon"):
        _device(f"atc3dg://?lib={fake_lib}").open()


def test_a_rate_the_tracker_refuses_is_an_error(fake_lib: Path) -> None:
    device = _device(f"atc3dg://?lib={fake_lib}&rate=500")
    with pytest.raises(DeviceError, match="MEASUREMENT_RATE=500"):
        device.open()


@pytest.mark.parametrize("query, message", [("range=50", "36, 72 or 144"), ("hemisphere=up", "hemisphere"),
                                            ("metric=2", "metric must be"), ("sensors=5", "sensors must be")])
def test_bad_settings_are_refused(query: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        Atc3dgEmHT("emht", DeviceUrl.parse(f"atc3dg://?{query}"), DeviceContext(HostClock(0), 0))
