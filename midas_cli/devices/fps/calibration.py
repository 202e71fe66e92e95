"""Per-pedal press/release thresholds for the FPS board (the paper's "brief per-pedal calibration").

Live: measure every channel at rest, then each mapped pedal pressed and held, one after the other
(:class:`LiveCalibration` reads the board; the command does the prompting). From a session: split each
mapped channel's recorded voltages into a rest and a pressed cluster (Otsu's threshold).

Either way, per channel: ``rest_v`` = 99.5th percentile of the rest samples, ``level_v`` = 75th
percentile of the pressed samples, span = level_v - rest_v. A channel separates when span >= 0.3 V;
then ``press_v = rest_v + 0.4 span`` and ``release_v = rest_v + 0.2 span`` (hysteresis between them).
A channel that does not separate keeps its previous thresholds and is flagged. Voltages are volts at
the ADC input (10-bit counts, Vcc 5 V).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from midas_cli.clock import HostClock
from midas_cli.devices.base import DeviceContext, DeviceUrl
from midas_cli.devices.fps.driver import FpsDevice
from midas_cli.devices.pedals import PedalThresholds, adc_to_volts
from midas_cli.errors import ConfigError, DeviceError, SessionError
from midas_cli.session.reader import Session

MIN_SEPARATION_V = 0.3
PRESS_FRACTION = 0.4
RELEASE_FRACTION = 0.2
REST_PERCENTILE = 99.5
LEVEL_PERCENTILE = 75.0
MIN_PRESSED_SAMPLES = 5


@dataclass(frozen=True)
class ChannelCalibration:
    """One mapped channel's result (volts). ``press_v``/``release_v`` are what will be used."""

    channel: int
    pedal: str
    rest_v: float
    level_v: float | None
    press_v: float
    release_v: float
    separated: bool
    note: str = ""


@dataclass(frozen=True)
class FpsCalibration:
    """Results of the mapped channels and the thresholds of every channel of the device."""

    channels: tuple[ChannelCalibration, ...]
    thresholds: PedalThresholds
    source: str

    @property
    def flagged(self) -> list[int]:
        """Mapped channels that did not separate (they kept their previous thresholds)."""
        return [c.channel for c in self.channels if not c.separated]

    def to_json(self) -> dict[str, Any]:
        return {"source": self.source, "channels": [asdict(c) for c in self.channels], "flagged": self.flagged,
                "press_v": list(self.thresholds.press_v), "release_v": list(self.thresholds.release_v)}


def channel_calibration(channel: int, pedal: str, rest: np.ndarray, pressed: np.ndarray,
                        previous: tuple[float, float]) -> ChannelCalibration:
    """Thresholds of one channel from its rest samples and pressed samples (volts, 1-D each)."""
    rest_v = float(np.percentile(rest, REST_PERCENTILE))
    if len(pressed) < MIN_PRESSED_SAMPLES:
        return ChannelCalibration(channel, pedal, rest_v, None, *previous, False, "never pressed")
    level_v = float(np.percentile(pressed, LEVEL_PERCENTILE))
    span = level_v - rest_v
    if span < MIN_SEPARATION_V:
        note = f"pressed level {level_v:.2f} V is within {MIN_SEPARATION_V} V of rest {rest_v:.2f} V"
        return ChannelCalibration(channel, pedal, rest_v, level_v, *previous, False, note)
    return ChannelCalibration(channel, pedal, rest_v, level_v, round(rest_v + PRESS_FRACTION * span, 3),
                              round(rest_v + RELEASE_FRACTION * span, 3), True)


def combine(results: list[ChannelCalibration], previous: PedalThresholds, source: str) -> FpsCalibration:
    """All channels' thresholds: calibrated where mapped, previous elsewhere."""
    press, release = list(previous.press_v), list(previous.release_v)
    for result in results:
        press[result.channel - 1], release[result.channel - 1] = result.press_v, result.release_v
    return FpsCalibration(tuple(results), PedalThresholds(tuple(press), tuple(release)), source)


def calibrate_live(rest: np.ndarray, presses: dict[int, np.ndarray], pedals: dict[int, str],
                   previous: PedalThresholds) -> FpsCalibration:
    """rest (N, channels) volts with feet off; presses: channel -> (M, channels) volts while it was held."""
    results = []
    for channel, pedal in sorted(pedals.items()):
        window = presses[channel]
        result = channel_calibration(channel, pedal, rest[:, channel - 1], window[:, channel - 1],
                                     _previous(previous, channel))
        others = _also_rose(rest, window, channel, pedals)
        if others:
            note = f"{result.note}; " if result.note else ""
            result = ChannelCalibration(**{**asdict(result), "note": note + f"also rose: channel(s) {others}"})
        results.append(result)
    return combine(results, previous, "live")


def _also_rose(rest: np.ndarray, window: np.ndarray, channel: int, pedals: dict[int, str]) -> list[int]:
    """Other mapped channels that rose while ``channel`` was held (crosstalk or a wrong mapping)."""
    rose = []
    for other in sorted(pedals):
        if other != channel:
            level = np.percentile(window[:, other - 1], LEVEL_PERCENTILE)
            if level - np.percentile(rest[:, other - 1], REST_PERCENTILE) >= MIN_SEPARATION_V:
                rose.append(other)
    return rose


def otsu_split(volts: np.ndarray, bins: int = 256) -> float:
    """The threshold (volts) that maximises the between-class variance of a 1-D sample."""
    low, high = float(volts.min()), float(volts.max())
    if high - low < 1e-9:
        return high + 1e-9
    counts, edges = np.histogram(volts, bins=bins, range=(low, high))
    centres = (edges[:-1] + edges[1:]) / 2
    weight0 = np.cumsum(counts)[:-1]  # samples at or below each candidate split (after bin i)
    weight1 = counts.sum() - weight0
    sum0 = np.cumsum(counts * centres)[:-1]
    total = float(np.sum(counts * centres))
    with np.errstate(divide="ignore", invalid="ignore"):
        between = weight0 * weight1 * (sum0 / weight0 - (total - sum0) / weight1) ** 2
    return float(edges[1:-1][int(np.nanargmax(between))])


def calibrate_from_session(path: Path | str, device: str, pedals: dict[int, str],
                           previous: PedalThresholds) -> FpsCalibration:
    """Thresholds of the mapped channels from the stream ``device`` of a recorded session."""
    session = Session.open(path)
    if device not in session.stream_names:
        raise SessionError(f"{session.path} has no stream {device!r} (streams: {', '.join(session.stream_names)}); "
                           "pass --device with the pedal board's name")
    frame = session.read_stream(device)
    results = []
    for channel, pedal in sorted(pedals.items()):
        column = f"ch{channel}_adc"
        if column not in frame:
            raise SessionError(f"{session.path}: stream {device!r} has no column {column} (pedal {pedal!r})")
        volts = np.asarray(adc_to_volts(frame[column].dropna().to_numpy()), dtype=float)
        if volts.size == 0:
            raise SessionError(f"{session.path}: stream {device!r} has no samples")
        split = otsu_split(volts)
        results.append(channel_calibration(channel, pedal, volts[volts < split], volts[volts >= split],
                                           _previous(previous, channel)))
    return combine(results, previous, str(session.path))


def _previous(thresholds: PedalThresholds, channel: int) -> tuple[float, float]:
    return thresholds.press_v[channel - 1], thresholds.release_v[channel - 1]


class LiveCalibration:
    """The board opened for calibration: :meth:`measure` collects volts for a while."""

    def __init__(self, url: str, device: str = "fps") -> None:
        parsed = DeviceUrl.parse(url)
        if parsed.scheme != "fps":
            raise ConfigError(f"live calibration needs the board's fps:// URL, got {url!r} (or use --session)")
        clock = HostClock.anchored_now()
        self.device = FpsDevice(device, parsed, DeviceContext(clock, clock.now_ns()))
        self.channels: int = self.device.params["channels"]

    def open(self) -> dict[str, Any]:
        """Connect (the stream stays paused until :meth:`measure`); returns what the board says about itself."""
        info = self.device.open()
        self.device.pause()
        return info

    def close(self) -> None:
        self.device.close()

    def measure(self, seconds: float, on_sample: Callable[[float, np.ndarray], None]) -> np.ndarray:
        """Volts (N, channels) over ``seconds`` from a fresh start of the stream (nothing recorded while the
        operator read a prompt); ``on_sample(elapsed_s, latest_volts)`` after each read."""
        self.device.restart()
        start = time.monotonic()
        rows: list[tuple] = []
        while (elapsed := time.monotonic() - start) < seconds:
            new = self.device.read().get(self.device.name, [])
            rows += new
            if new:
                on_sample(elapsed, self._volts(new[-1:])[0])
        self.device.pause()
        if not rows:
            raise DeviceError(f"no samples from {self.device.port} in {seconds:g} s (is the board streaming?)")
        return self._volts(rows)

    def _volts(self, rows: list[tuple]) -> np.ndarray:
        counts = np.array([row[3:3 + self.channels] for row in rows], dtype=float)
        return np.asarray(adc_to_volts(counts), dtype=float)
