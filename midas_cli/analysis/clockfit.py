"""Timestamps with their error bars: each stream's host stamps fitted against the device's own clock.

midas stamps a sample with the host clock when its bytes are read (``t_host_ns``), so a stamp carries
the transport's delay and its jitter (a USB-serial adapter holds bytes up to its latency timer, a busy
host reads late). Most devices also send a clock of their own, steady but on another time base: the
pedal board's ``micros()`` (wrapping at 2^32), the trakSTAR's record time, the camera's timestamp, the
sender's LSL clock; a device without one (the FOB, whose ``t_device_s`` stays empty, a video frame
clock) counts samples at a nominal rate. Over a session the two are related by a line, ``host = offset + (1 + drift) * device``, broken
where the device restarted (a reconnect, a wrap the counter cannot explain). Fitting that line per
segment, robustly (the pyxdf jitter-removal idea, with outliers dropped: a sample read a second late
must not tilt the line), gives

* the *fitted* host time of every sample: the stamps without their jitter (``align --times fitted``);
* the *jitter*: residuals of every raw stamp about the line (sd, p99 and max of |residual|), in ms
  (the outliers left out of the fit count here: they are real timestamp error);
* the *drift* of the device's clock against the host's, in ppm (for a sample counter: how far the
  device's true rate is from its nominal one).

The raw stamps stay as recorded; this module is pure (numpy on arrays) and writes nothing.
Host delays are one-sided (a stamp is never early), so the line sits at the mean delay, not the
minimum: the fitted times are smoother, not earlier. What remains constant (the mean transport delay)
no fit can see; ``midas eval sync`` measures offsets between streams from shared events.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Sequence

import numpy as np

UNIT_SECONDS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
WRAP_US = 1 << 32  # an Arduino's micros() counter
BREAK_GAP_S = 1.0  # a jump of either clock over this much (and over 20 periods) starts a new segment
BREAK_GAP_PERIODS = 20
OUTLIER_MADS = 5.0  # residuals beyond this many robust sd are left out of the next fit
FIT_ROUNDS = 4
MIN_SEGMENT = 10  # samples; a shorter segment keeps its raw stamps


@dataclass(frozen=True)
class ClockSource:
    """Where a stream's device time comes from: a column (with its unit in seconds), else ``seq`` at a
    nominal rate."""

    column: str | None
    seconds_per_unit: float
    wraps_at: int | None = None

    def describe(self) -> str:
        if self.column is None:
            return f"seq at {1.0 / self.seconds_per_unit:g} Hz (no device clock)"
        return self.column + (f" (wraps at 2^{int(math.log2(self.wraps_at))})" if self.wraps_at else "")


@dataclass
class ClockFit:
    """One stream's fit. Times in ms; drift in ppm (positive: the device's clock runs slow against the
    host's, i.e. one device second lasts longer on the host). ``fitted_ns``: every sample's fitted host
    time (raw where no segment could be fitted); not part of the JSON."""

    clock: str
    samples: int
    segments: int
    fitted_samples: int
    outliers: int
    drift_ppm: float | None
    jitter_sd_ms: float | None
    jitter_p99_ms: float | None
    jitter_max_ms: float | None
    fitted_ns: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, np.int64))

    def to_json(self) -> dict[str, Any]:
        document = asdict(self)
        document.pop("fitted_ns")
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in document.items()}


def clock_source(columns: Sequence[Any], nominal_rate_hz: float | None) -> ClockSource | None:
    """The stream's device clock: its first numeric column marked ``clock="device"`` with a time unit,
    else ``seq`` at the nominal rate; None for an event stream without a device clock."""
    for column in columns:
        if getattr(column, "clock", None) == "device" and column.dtype in ("int", "float") \
                and column.unit in UNIT_SECONDS:
            wraps = WRAP_US if column.unit == "us" and "wrap" in (column.description or "") else None
            return ClockSource(column.name, UNIT_SECONDS[column.unit], wraps)
    if nominal_rate_hz:
        return ClockSource(None, 1.0 / nominal_rate_hz)
    return None


def device_seconds(table: np.ndarray, source: ClockSource) -> np.ndarray:
    """The device time of every row in seconds (NaN where the device sent none), a wrapping counter
    unwrapped (each drop by more than half its range counts one wrap)."""
    raw = np.asarray(table["seq"] if source.column is None else table[source.column], dtype=np.float64)
    if source.wraps_at:
        drops = np.diff(raw, prepend=raw[:1]) < -source.wraps_at / 2
        raw = raw + np.cumsum(drops) * float(source.wraps_at)
    return raw * source.seconds_per_unit


def segment_bounds(device_s: np.ndarray, host_s: np.ndarray, period_s: float | None) -> list[tuple[int, int]]:
    """[start, stop) row ranges over which one line can hold: broken where the device clock goes back or
    where either clock jumps by more than BREAK_GAP_S and BREAK_GAP_PERIODS periods (a reconnect)."""
    if len(device_s) == 0:
        return []
    gap = max(BREAK_GAP_S, BREAK_GAP_PERIODS * (period_s or 0.0))
    d_dev, d_host = np.diff(device_s), np.diff(host_s)
    breaks = np.flatnonzero((d_dev < 0) | (d_dev > gap) | (np.abs(d_host) > gap) | ~np.isfinite(d_dev)) + 1
    edges = [0, *breaks.tolist(), len(device_s)]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def robust_line(x: np.ndarray, y: np.ndarray) -> tuple[float, float, np.ndarray]:
    """``y ~ a + b x`` by least squares, refitted FIT_ROUNDS times without the points beyond OUTLIER_MADS
    robust sd of the residuals. Returns (a, b, inlier mask). x and y should be centred (float64)."""
    keep = np.ones(len(x), dtype=bool)
    a, b = float(np.mean(y)), 0.0
    for _ in range(FIT_ROUNDS):
        if keep.sum() < 2:
            break
        b, a = np.polyfit(x[keep], y[keep], 1)
        residual = y - (a + b * x)
        mad = np.median(np.abs(residual[keep] - np.median(residual[keep])))
        scale = 1.4826 * mad
        if scale <= 0:
            break
        new_keep = np.abs(residual - np.median(residual[keep])) <= OUTLIER_MADS * scale
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    return float(a), float(b), keep


def fit_clock(host_ns: np.ndarray, device_s: np.ndarray, source: ClockSource,
              period_s: float | None = None) -> ClockFit:
    """Fit host time against device time per segment (see the module docstring). ``host_ns`` (N,) int64,
    ``device_s`` (N,) float seconds (NaN: none sent); ``period_s`` the nominal sample period, if any."""
    host_ns = np.asarray(host_ns, dtype=np.int64)
    fitted = host_ns.copy()
    usable = np.isfinite(device_s)
    rows = np.flatnonzero(usable)
    residuals: list[np.ndarray] = []
    drifts: list[tuple[float, int]] = []
    segments = outliers = 0
    if len(rows):
        host_s = (host_ns[rows] - host_ns[rows[0]]) / 1e9
        for start, stop in segment_bounds(device_s[rows], host_s, period_s):
            segments += 1
            if stop - start < MIN_SEGMENT:
                continue
            x = device_s[rows[start:stop]] - device_s[rows[start]]
            base = host_ns[rows[start]]
            y = (host_ns[rows[start:stop]] - base) / 1e9
            x0, y0 = float(np.mean(x)), float(np.mean(y))
            a, b, keep = robust_line(x - x0, y - y0)
            line = y0 + a + b * (x - x0)
            fitted[rows[start:stop]] = base + np.round(line * 1e9).astype(np.int64)
            residuals.append((y - line) * 1e3)  # all of them: a late read is real timestamp error
            outliers += int((~keep).sum())
            drifts.append(((b - 1.0) * 1e6, stop - start))
    return _summary(source, len(host_ns), segments, fitted, residuals, drifts, outliers)


def _summary(source: ClockSource, samples: int, segments: int, fitted: np.ndarray, residuals: list[np.ndarray],
             drifts: list[tuple[float, int]], outliers: int) -> ClockFit:
    if not residuals:
        return ClockFit(source.describe(), samples, segments, 0, outliers, None, None, None, None, fitted)
    ms = np.concatenate(residuals)
    weight = sum(n for _, n in drifts)
    drift = sum(d * n for d, n in drifts) / weight
    return ClockFit(source.describe(), samples, segments, int(sum(len(r) for r in residuals)), outliers,
                    float(drift), float(np.std(ms)), float(np.percentile(np.abs(ms), 99)),
                    float(np.abs(ms).max()), fitted)


def fit_stream(table: np.ndarray, columns: Sequence[Any], nominal_rate_hz: float | None) -> ClockFit | None:
    """The fit of one stream as ``Session.read_columns`` gives it (None: an event stream with no clock).
    A device-clock column that no row filled (the FOB's ``t_device_s``: its records carry no time)
    gives way to ``seq`` at the nominal rate."""
    source = clock_source(columns, nominal_rate_hz)
    if source is None or len(table) == 0:
        return None
    device_s = device_seconds(table, source)
    if source.column is not None and nominal_rate_hz and not np.isfinite(device_s).any():
        source = ClockSource(None, 1.0 / nominal_rate_hz)
        device_s = device_seconds(table, source)
    period = 1.0 / nominal_rate_hz if nominal_rate_hz else None
    return fit_clock(np.asarray(table["t_host_ns"], np.int64), device_s, source, period)
