"""fob:// latency: the last record of a burst is accepted once the line is idle after it, not a cycle later,
and an extra byte right after a record is still rejected (decoder and driver, over ptys)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest
import serial

from midas_cli.clock import HostClock
from midas_cli.devices.base import DeviceContext, DeviceUrl
from midas_cli.devices.registry import describe_device
from midas_cli.devices.trakstar import protocol as fob
from midas_cli.devices.trakstar.driver import READ_TIMEOUT_S, FobEmHT
from midas_cli.devices.trakstar.emulator import EmulatorConfig, TrakstarEmulator
from midas_cli.errors import ConfigError

VALUES = np.array([[100.0, -50.0, 250.0, 45.0, -30.0, 170.0],
                   [-300.0, 20.0, 0.0, -179.0, 89.0, 0.0]])


def _records(values: np.ndarray = VALUES) -> list[bytes]:
    words = fob.words_from_values(values, 36)
    return [fob.encode_record(w, address) for address, w in enumerate(words, start=1)]


# ---- decoder ---------------------------------------------------------------------------------------

def test_the_last_record_of_a_burst_waits_until_idle_accept_or_lookahead() -> None:
    a, b = _records()
    decoder = fob.RecordDecoder(sensors=2, range_in=36)
    assert [r.address for r in decoder.feed(a + b, 7)] == [1], "b has no lookahead byte yet"
    assert decoder.pending and decoder.counts.idle_accepted == 0
    [record] = decoder.accept_pending()
    assert record.address == 2 and record.t_host_ns == 7, "time of the read that completed it"
    assert record.values == fob.RecordDecoder(sensors=2, range_in=36).feed(b + a, 0)[0].values
    assert not decoder.pending and decoder.accept_pending() == []
    assert decoder.counts.idle_accepted == 1 and decoder.counts.records == 2
    assert [r.address for r in decoder.feed(a + b + a, 9)] == [1, 2], "next burst decodes as before"
    assert decoder.counts.discarded_bytes == 0


def test_an_incomplete_record_is_never_pending() -> None:
    a, b = _records()
    decoder = fob.RecordDecoder(sensors=2, range_in=36)
    decoder.feed(a + b[:5] + b[6:], 0)  # a byte of b lost: 12 bytes
    assert not decoder.pending and decoder.accept_pending() == []
    assert decoder.counts.records == 1


@pytest.mark.parametrize("same_read", [True, False])
def test_an_inserted_byte_right_after_a_record_is_still_rejected(same_read: bool) -> None:
    a, b = _records()
    decoder = fob.RecordDecoder(sensors=2, range_in=36)
    if same_read:
        records = decoder.feed(a + b + b"\x05", 0)
    else:  # the byte arrived after the read that completed b, before the line went idle
        records = decoder.feed(a + b, 0)
        assert decoder.pending
        records += decoder.feed(b"\x05", 1)
    assert [r.address for r in records] == [1]
    assert not decoder.pending and decoder.accept_pending() == []
    assert decoder.counts.reasons["record too long"] == 1 and decoder.counts.discarded_bytes == 14
    assert [r.address for r in decoder.feed(a + b + a, 2)] == [1, 2]


def test_idle_accept_still_frames_address_and_elevation() -> None:
    a, _ = _records()
    decoder = fob.RecordDecoder(sensors=2, range_in=36)
    decoder.feed(a[:-1] + bytes([9]), 0)  # address 9 of 2 sensors
    assert decoder.pending and decoder.accept_pending() == []
    assert decoder.counts.reasons["address out of range"] == 1
    assert decoder.counts.discarded_bytes == fob.RECORD_BYTES and decoder.counts.idle_accepted == 0


def test_a_stray_byte_after_an_idle_accepted_record_is_discarded_and_counted() -> None:
    a, b = _records()
    decoder = fob.RecordDecoder(sensors=2, range_in=36)
    decoder.feed(a + b, 0)
    decoder.accept_pending()
    records = decoder.feed(b"\x11" + a + b + a, 1)
    assert [r.address for r in records] == [1, 2] and records[0].discarded_before == 1
    assert decoder.counts.discarded_bytes == 1


# ---- driver ----------------------------------------------------------------------------------------

@pytest.fixture
def slow_emulator(tmp_path: Path):
    emu = TrakstarEmulator(EmulatorConfig(link=str(tmp_path / "trakstar"))).start()
    yield emu
    emu.stop()


def _rows_with_state(device: FobEmHT, emu: TrakstarEmulator, wanted: int) -> list[tuple[int, int, int]]:
    """At each read that returned rows: (rows so far, cycles the emulator had sent, bytes the decoder holds)."""
    seen, rows, deadline = [], 0, time.monotonic() + 20
    while len(seen) < wanted and time.monotonic() < deadline:
        got = device.read().get("emht", [])
        if got:
            rows += len(got)
            seen.append((rows, emu.summary()["stream_groups_sent"], len(device._decoder._buffer)))
    return seen


def test_a_cycle_reaches_read_before_the_next_cycle_is_sent(slow_emulator) -> None:
    """At 4 Hz each group is followed by 250 ms of silence: its row comes out on the idle window, with no
    byte of the next cycle received (or even sent)."""
    clock = HostClock.anchored_now()
    device = FobEmHT("emht", DeviceUrl.parse(f"fob://{slow_emulator.path}?rate=4&sensors=4"), DeviceContext(clock, clock.now_ns()))
    device.open()
    try:
        seen = _rows_with_state(device, slow_emulator, 3)
    finally:
        device.close()
    assert len(seen) == 3 and [rows for rows, _, _ in seen] == [1, 2, 3]
    assert all(sent <= rows and held == 0 for rows, sent, held in seen), seen
    assert device._decoder.counts.idle_accepted >= 3
    assert device.counters.corrupt == 0 and device.counters.discarded_bytes == 0


def test_with_idle_0_a_cycle_waits_for_the_next_cycles_first_byte(slow_emulator) -> None:
    clock = HostClock.anchored_now()
    url = DeviceUrl.parse(f"fob://{slow_emulator.path}?rate=4&sensors=4&idle=0")
    device = FobEmHT("emht", url, DeviceContext(clock, clock.now_ns()))
    device.open()
    try:
        seen = _rows_with_state(device, slow_emulator, 2)
    finally:
        device.close()
    assert len(seen) == 2 and all(held > 0 for _, _, held in seen), "the next record had begun to arrive"
    assert device._decoder.counts.idle_accepted == 0


def _raw_pty_device(idle_ms: float) -> tuple[FobEmHT, int, int]:
    """A driver reading a bare pty (no configuration handshake): the test writes the tracker's bytes."""
    master, slave = os.openpty()
    os.set_blocking(master, False)
    clock = HostClock.anchored_now()
    device = FobEmHT("emht", DeviceUrl.parse(f"fob://{os.ttyname(slave)}?sensors=2&idle={idle_ms}&timeout=5"), DeviceContext(clock, 0))
    device._port = serial.serial_for_url(os.ttyname(slave), timeout=READ_TIMEOUT_S)
    device._fd = device._port_fd()
    device._last_data = time.monotonic()
    return device, master, slave


def _read_rows(device: FobEmHT, seconds: float, wanted: int | None = None) -> list[tuple]:
    """Rows read for ``seconds``, or until ``wanted`` rows came."""
    rows, deadline = [], time.monotonic() + seconds
    while time.monotonic() < deadline and (wanted is None or len(rows) < wanted):
        rows += device.read().get("emht", [])
    return rows


def test_a_byte_inside_the_idle_window_is_framed_not_skipped() -> None:
    """idle=400 ms: a byte written a few reads after the group (well inside the window) makes the last
    record fail framing (too long); that sensor is empty and counted, nothing wrong reaches a row."""
    device, master, slave = _raw_pty_device(400)
    a, b = _records()
    try:
        os.write(master, a + b)
        rows: list[tuple] = []
        for _ in range(10):  # each read blocks at most 5 ms: all well inside the 400 ms window
            rows += device.read().get("emht", [])
            if device._decoder.pending:
                break
        for _ in range(3):  # the line is quiet, but not yet for 400 ms
            rows += device.read().get("emht", [])
        assert rows == [] and device._decoder.pending
        os.write(master, b"\x05")
        rows += _read_rows(device, 0.6)  # longer than the window: still nothing accepted
        assert rows == [] and not device._decoder.pending
        os.write(master, a + b)
        rows += _read_rows(device, 4.0, wanted=2)
    finally:
        device.close()
        os.close(master)
        os.close(slave)
    assert len(rows) == 2 and rows[0][0] + 1 == rows[1][0]
    assert rows[0][3] is not None and rows[0][10:16] == (None,) * 6, "cycle 0: sensor 2 rejected"
    assert rows[1][10] == pytest.approx(VALUES[1][0], abs=0.2), "cycle 1 complete, accepted on idle"
    assert device._decoder.counts.reasons["record too long"] == 1 and device.counters.corrupt == 1


def test_idle_window_defaults_to_16_byte_times_and_is_validated() -> None:
    assert describe_device("emht", "fob:///dev/x?baud=115200").settings()["idle"] == pytest.approx(1.389, abs=1e-3)
    assert describe_device("emht", "fob:///dev/x?baud=57600").settings()["idle"] == pytest.approx(2.778, abs=1e-3)
    assert describe_device("emht", "fob:///dev/x?idle=0").settings()["idle"] == 0
    assert describe_device("emht", "fob:///dev/x?idle=0.2").idle_s == pytest.approx(0.0002)
    with pytest.raises(ConfigError, match="idle must be"):
        describe_device("emht", "fob:///dev/x?idle=-1")
    with pytest.raises(ConfigError, match="idle must be"):
        describe_device("emht", "fob:///dev/x?idle=2000&timeout=1")
