"""Timestamps with error bars (issue 26 item 1): the per-stream fit of host stamps against the device's
clock recovers a known drift, offset and jitter on synthetic stamps, through wraps, reconnects and
late reads; `midas align --times fitted` uses it and aligned.json says what it found."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from midas_cli.analysis.clockfit import WRAP_US, ClockSource, clock_source, device_seconds, fit_clock, fit_stream
from midas_cli.session.schema import SEQ, T_HOST, Column
from helpers.cli import midas

RATE = 250.0
MICROS = ClockSource("t_device_us", 1e-6, WRAP_US)


def _stamps(seconds: float, drift_ppm: float, jitter_ms: float, seed: int = 3, start_us: int = WRAP_US - 2_000_000):
    """A pedal board: micros() starting 2 s before its wrap; the host stamps each sample at true time
    + one-sided exponential delay; the board's clock runs ``drift_ppm`` slow against the host's."""
    rng = np.random.default_rng(seed)
    n = int(seconds * RATE)
    board_s = np.arange(n) / RATE
    true_host_s = 1_000.0 + board_s * (1 + drift_ppm * 1e-6)
    delay_s = rng.exponential(jitter_ms / 1e3, n)
    host_ns = np.round((true_host_s + delay_s) * 1e9).astype(np.int64)
    micros = (np.round(board_s * 1e6).astype(np.int64) + start_us) % WRAP_US
    return host_ns, micros, true_host_s


def test_a_known_drift_offset_and_jitter_are_recovered_through_a_wrap() -> None:
    host_ns, micros, true_host_s = _stamps(120, drift_ppm=50, jitter_ms=0.5)
    table = np.zeros(len(micros), dtype=[("seq", "i8"), ("t_host_ns", "i8"), ("t_device_us", "i8")])
    table["t_device_us"] = micros
    device_s = device_seconds(table, MICROS)
    assert np.all(np.diff(device_s) > 0)  # the wrap 2 s in is unwrapped
    fit = fit_clock(host_ns, device_s, MICROS, 1 / RATE)
    assert fit.segments == 1 and fit.fitted_samples == len(micros)
    assert fit.drift_ppm == pytest.approx(50, abs=1.0)
    assert fit.jitter_sd_ms == pytest.approx(0.5, rel=0.1)  # an exponential's sd is its mean
    raw_error = host_ns / 1e9 - true_host_s
    fitted_error = fit.fitted_ns / 1e9 - true_host_s
    # the line sits at the mean delay: the fitted times keep that constant but lose the jitter
    assert np.std(fitted_error) < np.std(raw_error) / 20
    assert np.mean(fitted_error) == pytest.approx(np.mean(raw_error), abs=5e-5)


def test_late_reads_do_not_tilt_the_line_and_a_reconnect_starts_a_segment() -> None:
    host_ns, micros, true_host_s = _stamps(60, drift_ppm=-20, jitter_ms=0.2, start_us=0)
    host_ns[[500, 3000, 9000]] += 800_000_000  # three reads held up by most of a second
    restart = 7500  # the board resets: micros() starts again from 0 after a 3-s outage
    micros[restart:] = np.round((np.arange(len(micros) - restart) / RATE) * 1e6).astype(np.int64)
    host_ns[restart:] += 3_000_000_000
    device_s = micros.astype(np.float64) / 1e6
    fit = fit_clock(host_ns, device_s, ClockSource("t_device_us", 1e-6), 1 / RATE)
    assert fit.segments == 2 and 3 <= fit.outliers < 0.03 * len(host_ns)  # the late reads and the far tail
    assert fit.drift_ppm == pytest.approx(-20, abs=2.0) and fit.jitter_p99_ms < 1.5
    good = np.ones(len(host_ns), bool)
    good[[500, 3000, 9000]] = False
    shift = np.where(np.arange(len(host_ns)) >= restart, 3.0, 0.0)
    assert np.abs(fit.fitted_ns[good] / 1e9 - shift[good] - true_host_s[good] - 0.0002).max() < 5e-4


def test_the_clock_source_is_the_device_column_else_seq_at_the_nominal_rate() -> None:
    with_clock = [SEQ, T_HOST, Column("t_device_s", "float", "s", 6, clock="device"), Column("x_mm", "float", "mm")]
    assert clock_source(with_clock, 240.0) == ClockSource("t_device_s", 1.0)
    assert clock_source([SEQ, T_HOST, Column("x_mm", "float", "mm")], 30.0) == ClockSource(None, 1 / 30.0)
    assert clock_source([SEQ, T_HOST, Column("text", "text")], None) is None  # markers: no clock to fit


def test_the_sync_statement_names_the_clock_the_fit_used_not_an_empty_declared_column(tmp_path: Path) -> None:
    """A FOB stream declares t_device_s (never filled): once align has fitted it, the statement says
    seq at the nominal rate, as the fit did, not a device clock the records never carried."""
    from midas_cli.session.sync_statement import recorded_statement, statement

    manifest = {"streams": {"emht": {"nominal_rate_hz": 220.0, "columns": [
        {"name": "seq"}, {"name": "t_host_ns"}, {"name": "t_device_s", "clock": "device"}]}}}
    assert recorded_statement(manifest)["streams"]["emht"]["device_clock"] == "t_device_s"  # as declared
    (tmp_path / "derived").mkdir()
    fit = {"clock": "seq at 220 Hz (no device clock)", "samples": 10, "drift_ppm": 1.0}
    (tmp_path / "derived" / "aligned.json").write_text(json.dumps({"clock_fit": {"emht": fit}}), encoding="utf-8")
    entry = statement(tmp_path, manifest)["streams"]["emht"]
    assert entry["device_clock"] == "seq at 220 Hz (no device clock)" and entry["fit"] == fit


def test_an_empty_device_clock_column_gives_way_to_seq_at_the_nominal_rate() -> None:
    """fob:// declares t_device_s but its records carry no time: the fit uses seq at the nominal rate."""
    host_ns, _, true_host_s = _stamps(20, drift_ppm=0, jitter_ms=0.3)
    table = np.zeros(len(host_ns), dtype=[("seq", "i8"), ("t_host_ns", "i8"), ("t_device_s", "f8")])
    table["seq"], table["t_host_ns"], table["t_device_s"] = np.arange(len(host_ns)) + 40, host_ns, np.nan
    columns = [SEQ, T_HOST, Column("t_device_s", "float", "s", 6, clock="device")]
    fit = fit_stream(table, columns, RATE)
    assert fit is not None and fit.clock == f"seq at {RATE:g} Hz (no device clock)"
    assert fit.fitted_samples == len(host_ns) and fit.drift_ppm == pytest.approx(0, abs=5)
    assert np.std(fit.fitted_ns / 1e9 - true_host_s) < 0.3e-3 / 10
    table["t_device_s"][5] = 1.0  # one filled value: the column is the clock (and too sparse to fit)
    assert fit_stream(table, columns, RATE).fitted_samples == 0


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("clockfit")
    made = midas("simulate", "dataset", "--trials", "1", "--max-seconds", "6", "--out", str(root), check=True)
    return Path(made.stdout.split()[-1])


def test_align_reports_each_streams_fit_and_can_use_the_fitted_times(simulated: Path) -> None:
    midas("align", str(simulated), check=True)
    raw = json.loads((simulated / "derived" / "aligned.json").read_text())
    assert raw["times"] == "host"
    fits = raw["clock_fit"]
    assert {"video"} <= set(fits) and all(f["samples"] > 0 for f in fits.values())
    for entry in fits.values():
        if entry["fitted_samples"]:
            assert entry["jitter_sd_ms"] >= 0 and abs(entry["drift_ppm"]) < 10_000
    result = midas("align", str(simulated), "--times", "fitted")
    assert result.returncode == 0, result.stderr
    fitted = json.loads((simulated / "derived" / "aligned.json").read_text())
    assert fitted["times"] == "fitted" and fitted["clock_fit"] == fits
    info = midas("session", "info", str(simulated), "--json", check=True)
    assert json.loads(info.stdout)["streams"]["video"]["clock_fit"] == fits["video"]
    shown = midas("session", "info", str(simulated), check=True).stdout
    assert "clock video: host stamps vs t_device_s: drift" in shown
    bad = midas("align", str(simulated), "--times", "device")
    assert bad.returncode == 2 and "--times" in bad.stderr
