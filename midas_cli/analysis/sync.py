"""Pure synchronisation of sampled streams onto a frame clock: numpy (and a scipy spline) on arrays, no
session, no files, no threads. ``align`` builds the aligned table from these.

Times are host nanoseconds (int64) unless named ``_s``. ``associate`` picks the sample for each frame
(causal: latest at or before; nearest), ``coverage`` says how much of a stream a clock spans,
``associate_stream`` gathers a structured array's columns at the chosen rows, ``regular_frames`` makes
a regular clock spanning streams, ``fill_gaps`` fills gaps (spline / forward fill), ``downsample_rows``
keeps one frame per bin, ``velocity_mm_s`` differentiates on the clock and ``estimate_lag`` finds the
lag between two signals by cross-correlation.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from midas_cli.errors import SessionError


def associate(sample_ns: np.ndarray, frame_ns: np.ndarray, method: str, stale_ns: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index of the sample chosen for each frame, its validity and its offset.

    sample_ns (M,) ascending, frame_ns (N,) host ns. Returns idx (N,) int (clipped into range),
    valid (N,) bool, delta_ms (N,) float = sample time - frame time (NaN where invalid).
    """
    if len(sample_ns) == 0:
        return np.zeros(len(frame_ns), dtype=int), np.zeros(len(frame_ns), bool), np.full(len(frame_ns), np.nan)
    after = np.searchsorted(sample_ns, frame_ns, side="right")
    idx = after - 1  # latest sample at or before the frame
    if method == "nearest":
        nxt = np.minimum(after, len(sample_ns) - 1)
        prev = np.maximum(idx, 0)
        take_next = (idx < 0) | (np.abs(sample_ns[nxt] - frame_ns) < np.abs(frame_ns - sample_ns[prev]))
        idx = np.where(take_next, nxt, prev)
    valid = idx >= 0
    idx = np.clip(idx, 0, len(sample_ns) - 1)
    offset = sample_ns[idx] - frame_ns
    valid &= np.abs(offset) <= stale_ns
    return idx, valid, np.where(valid, offset / 1e6, np.nan)


def coverage(sample_ns: np.ndarray, frame_ns: np.ndarray) -> dict[str, Any]:
    """How much of a stream the frame clock covers: of its samples (sample_ns (M,) ascending, host ns)
    the count and share inside [first frame, last frame], and the share of its time span (first to
    last sample) inside that interval (1.0 for a single sample inside)."""
    if len(sample_ns) == 0 or len(frame_ns) == 0:
        return {"samples": int(len(sample_ns)), "samples_inside": 0, "samples_share": 0.0, "span_s": 0.0,
                "span_share": 0.0}
    first, last = int(frame_ns[0]), int(frame_ns[-1])
    inside = int(np.searchsorted(sample_ns, last, side="right") - np.searchsorted(sample_ns, first, side="left"))
    span = int(sample_ns[-1] - sample_ns[0])
    overlap = max(0, min(last, int(sample_ns[-1])) - max(first, int(sample_ns[0])))
    span_share = overlap / span if span > 0 else float(inside > 0)
    return {"samples": int(len(sample_ns)), "samples_inside": inside,
            "samples_share": round(inside / len(sample_ns), 4), "span_s": round(span / 1e9, 3),
            "span_share": round(span_share, 4)}


def associate_stream(table: np.ndarray, spec_columns: list[str], frame_ns: np.ndarray, method: str,
                     stale_ns: int, out: np.ndarray | None = None, covered: dict[str, Any] | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Values of ``spec_columns`` of a stream (structured array, see ``Session.read_columns``) at each
    frame, NaN where masked, as ``out`` (C, N) (row j = column j; allocated if None), and delta_ms (N,).
    Only the chosen rows are read, so a memory-mapped stream is never copied whole. ``covered``, if
    given, receives the stream's ``coverage`` by the frames."""
    sample_ns = np.ascontiguousarray(table["t_host_ns"], dtype=np.int64)  # one strided pass over the rows
    order = None
    if len(sample_ns) > 1 and (np.diff(sample_ns) < 0).any():
        order = np.argsort(sample_ns, kind="stable")
        sample_ns = sample_ns[order]
    if covered is not None:
        covered.update(coverage(sample_ns, frame_ns))
    idx, valid, delta = associate(sample_ns, frame_ns, method, stale_ns)
    values = np.empty((len(spec_columns), len(frame_ns))) if out is None else out
    if len(sample_ns):
        chosen = table.view(np.ndarray)[idx if order is None else order[idx]]  # whole rows, one pass
        for j, name in enumerate(spec_columns):
            values[j] = chosen[name]
        if not valid.all():
            values[:, ~valid] = np.nan
    else:
        values[:] = np.nan
    return values, delta


def regular_frames(data: dict[str, np.ndarray], rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """A regular clock at ``rate_hz`` from the first sample of any stream in ``data`` to the first tick at
    or after the last one: frame indices (N,) and host times (N,) ns (frame k at first + k / rate)."""
    times = [np.asarray(t["t_host_ns"], dtype=np.int64) for t in data.values() if len(t)]
    if not times:
        raise SessionError("no stream has samples: nothing to span with a regular clock")
    first, last = min(int(t.min()) for t in times), max(int(t.max()) for t in times)
    n = int(np.ceil((last - first) * rate_hz / 1e9 - 1e-9)) + 1
    frames = np.arange(n, dtype=np.int64)
    return frames, first + np.round(frames * 1e9 / rate_hz).astype(np.int64)


def velocity_mm_s(points: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """Central-difference velocity (N, 3) of points (N, 3) mm sampled at t_s (N,) s; NaN propagates."""
    if len(t_s) < 2:
        return np.full_like(points, np.nan)
    return np.gradient(points, t_s, axis=0)


def fill_gaps(t_s: np.ndarray, values: np.ndarray, max_spline_gap_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Fill NaN rows of ``values`` (N, D): cubic spline through the valid rows for gaps whose bounding
    valid frames are at most ``max_spline_gap_s`` apart, forward fill otherwise (also after the last
    valid row); rows before the first valid row stay NaN. Returns filled (N, D), fill code (N,) int
    (0 = original, 1 = spline, 2 = forward fill, -1 = still missing)."""
    valid = np.isfinite(values).all(axis=1)
    code = np.where(valid, 0, -1)
    filled = values.copy()
    if valid.sum() == 0:
        return filled, code
    good = np.flatnonzero(valid)
    nxt = np.searchsorted(good, np.arange(len(t_s)))  # index into good of the next valid row
    prev_row = good[np.clip(nxt - 1, 0, len(good) - 1)]
    has_prev = nxt > 0
    has_next = nxt < len(good)
    span = np.where(has_prev & has_next, t_s[good[np.clip(nxt, 0, len(good) - 1)]] - t_s[prev_row], np.inf)
    spline_rows = ~valid & has_prev & has_next & (span <= max_spline_gap_s)
    ffill_rows = ~valid & has_prev & ~spline_rows
    if spline_rows.any() and len(good) >= 2:
        filled[spline_rows] = cubic_spline(t_s[good], values[good], t_s[spline_rows])
        code[spline_rows] = 1
    filled[ffill_rows] = values[prev_row[ffill_rows]]
    code[ffill_rows] = 2
    return filled, code


def cubic_spline(x: np.ndarray, y: np.ndarray, at: np.ndarray) -> np.ndarray:
    """The not-a-knot cubic spline through (x, y) evaluated at ``at`` (x (M,) strictly ascending, y (M, D)).

    The same curve as ``scipy.interpolate.CubicSpline(x, y, axis=0)`` (its default end condition: the
    third derivative is continuous at the second and the second-to-last knot), solved here for the
    knots' first derivatives with one tridiagonal ``scipy.linalg.solve_banded`` so that ``midas align``
    does not import ``scipy.interpolate`` (a third of a second per process, more than aligning a
    10-minute session). Two knots give the line, three the parabola through them."""
    from scipy.linalg import solve_banded

    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float).reshape(len(x), -1)
    h = np.diff(x)
    slope = np.diff(y, axis=0) / h[:, None]
    n = len(x)
    if n == 2:
        m = np.vstack([slope[0], slope[0]])
    elif n == 3:  # not-a-knot on three knots: the one parabola through them
        curvature = (slope[1] - slope[0]) / (x[2] - x[0])
        m = np.vstack([slope[0] - curvature * h[0], slope[0] + curvature * h[0], slope[1] + curvature * h[1]])
    else:
        bands = np.zeros((3, n))  # rows: super-diagonal, diagonal, sub-diagonal (solve_banded's (1, 1) layout)
        rhs = np.empty((n, y.shape[1]))
        bands[1, 1:-1] = 2 * (h[:-1] + h[1:])
        bands[0, 2:] = h[:-1]
        bands[2, :-2] = h[1:]
        rhs[1:-1] = 3 * (h[1:, None] * slope[:-1] + h[:-1, None] * slope[1:])
        d0, d1 = x[2] - x[0], x[-1] - x[-3]
        bands[1, 0], bands[0, 1] = h[1], d0
        rhs[0] = ((h[0] + 2 * d0) * h[1] * slope[0] + h[0] ** 2 * slope[1]) / d0
        bands[1, -1], bands[2, -2] = h[-2], d1
        rhs[-1] = (h[-1] ** 2 * slope[-2] + (2 * d1 + h[-1]) * h[-2] * slope[-1]) / d1
        m = solve_banded((1, 1), bands, rhs, overwrite_ab=True, overwrite_b=True, check_finite=False)
    at = np.asarray(at, dtype=float)
    i = np.clip(np.searchsorted(x, at, side="right") - 1, 0, n - 2)
    width = h[i][:, None]
    u = ((at - x[i]) / h[i])[:, None]
    # cubic Hermite on [x_i, x_i+1] with end values y and end slopes m
    return ((2 * u**3 - 3 * u**2 + 1) * y[i] + (u**3 - 2 * u**2 + u) * width * m[i]
            + (-2 * u**3 + 3 * u**2) * y[i + 1] + (u**3 - u**2) * width * m[i + 1])


def downsample_rows(t_ns: np.ndarray, rate_hz: float | None) -> np.ndarray:
    """Indices of the frames kept at ``rate_hz``: the first frame of each 1/rate bin (all if None).

    Bin edges get a quarter-frame tolerance: frame times rounded to whole ns (frame 3 at 30 Hz is
    99 999 999 ns) must not slip into the previous bin and make the kept frames irregular."""
    if rate_hz is None or len(t_ns) == 0:
        return np.arange(len(t_ns))
    tolerance_ns = float(np.median(np.diff(t_ns))) / 4 if len(t_ns) > 1 else 0.0
    bins = np.floor((t_ns - t_ns[0] + tolerance_ns) * rate_hz / 1e9).astype(np.int64)
    return np.flatnonzero(np.r_[True, np.diff(bins) > 0])


def estimate_lag(reference: np.ndarray, signal: np.ndarray, rate_hz: float, max_lag_s: float = 0.5) -> float:
    """Lag in seconds by which ``signal`` trails ``reference`` (both (N,) or (N, D) on one uniform clock
    at ``rate_hz``): the shift maximising the summed normalised cross-correlation, refined to a
    fraction of a sample by a parabola through the peak. Positive = signal is late. NaN rows ignored."""
    ref = _standardise(np.asarray(reference, dtype=float).reshape(len(reference), -1))
    sig = _standardise(np.asarray(signal, dtype=float).reshape(len(signal), -1))
    max_shift = max(1, int(round(max_lag_s * rate_hz)))
    shifts = np.arange(-max_shift, max_shift + 1)
    scores = np.array([_shifted_correlation(ref, sig, s) for s in shifts])
    if not np.isfinite(scores).any():
        raise SessionError("cannot estimate a lag: the signals have no overlapping valid samples")
    best = int(np.nanargmax(scores))
    offset = 0.0
    if 0 < best < len(scores) - 1 and np.isfinite(scores[best - 1 : best + 2]).all():
        left, mid, right = scores[best - 1 : best + 2]
        denom = left - 2 * mid + right
        offset = 0.5 * (left - right) / denom if denom < 0 else 0.0
    return float((shifts[best] + offset) / rate_hz)


def _standardise(x: np.ndarray) -> np.ndarray:
    mean, std = np.nanmean(x, axis=0), np.nanstd(x, axis=0)
    return (x - mean) / np.where(std > 0, std, 1.0)


def _shifted_correlation(ref: np.ndarray, sig: np.ndarray, shift: int) -> float:
    """Mean of ref[t] * sig[t + shift] over rows where both are valid."""
    a, b = (ref[: len(ref) - shift], sig[shift:]) if shift >= 0 else (ref[-shift:], sig[: len(sig) + shift])
    product = a * b
    ok = np.isfinite(product)
    return float(product[ok].mean()) if ok.sum() > 10 else np.nan
