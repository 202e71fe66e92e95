"""Chunked, lazily generated schedules of the synthetic world: minimum-jerk knot curves, interval
(event) schedules, renewal processes and hold-and-reach knot sequences.

Every schedule is generated per fixed-length chunk of time, chunk k from ``make_chunk(k)`` alone, and
extended lazily up to the largest ``t`` seen, so values never depend on how time was batched.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np

log = logging.getLogger(__name__)

CHUNK_MARGIN_S = 1.0  # events (presses, occlusions) start and end at least this far from chunk edges


@dataclass(frozen=True)
class EventProfile:
    """Renewal process of timed events (pedal presses, detector occlusions), seconds.

    The gap from one event's end to the next event's start is ~ U(gap_min_s, gap_max_s); the first event
    of a chunk starts U(0, gap_max_s) after the chunk start; durations are ~ U(duration_min_s,
    duration_max_s). Events never span a chunk boundary.
    """

    gap_min_s: float
    gap_max_s: float
    duration_min_s: float
    duration_max_s: float


def minimum_jerk(s: np.ndarray) -> np.ndarray:
    """Minimum-jerk profile 10 s^3 - 15 s^4 + 6 s^5 for s in [0, 1] (zero velocity/acceleration at ends)."""
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s))


class ChunkedSchedule:
    """Arrays generated per time chunk and concatenated; chunk k comes from ``make_chunk(k)`` alone."""

    def __init__(self, chunk_s: float, make_chunk: Callable[[int], tuple[np.ndarray, ...]]) -> None:
        self._chunk_s = chunk_s
        self._make_chunk = make_chunk
        self._chunks: list[tuple[np.ndarray, ...]] = []
        self._fields: tuple[np.ndarray, ...] = ()

    def fields_covering(self, t: np.ndarray) -> tuple[np.ndarray, ...]:
        """The concatenated arrays of chunks 0 .. (chunk of max t) + 1."""
        last_chunk = int(t.max() // self._chunk_s) + 1 if t.size else 1
        if len(self._chunks) <= last_chunk:
            log.debug("extending schedule to chunk %d", last_chunk)
            while len(self._chunks) <= last_chunk:
                self._chunks.append(self._make_chunk(len(self._chunks)))
            self._fields = tuple(np.concatenate(parts) for parts in zip(*self._chunks))
        return self._fields


class KnotCurve(ChunkedSchedule):
    """Piecewise minimum-jerk curve through knots (times (K,), values (K, D)).

    ``make_chunk(k)`` returns the knots in [k * chunk_s, (k + 1) * chunk_s), the first exactly at
    k * chunk_s; the last segment of a chunk runs to the first knot of the next chunk.
    """

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """Curve values (N, D) at t (N,)."""
        times, values = self.fields_covering(t)
        start = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
        span = times[start + 1] - times[start]
        progress = minimum_jerk(np.clip((t - times[start]) / span, 0.0, 1.0))
        return values[start] + (values[start + 1] - values[start]) * progress[:, None]


class IntervalSchedule(ChunkedSchedule):
    """Non-overlapping intervals (starts (M,), ends (M,), params (M, P)), each inside one chunk."""

    def lookup(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(index (N,) of the interval at or before t, inside (N,) bool: start <= t < end)."""
        starts, ends = self.fields_covering(t)[:2]
        if starts.size == 0:
            return np.zeros(t.shape, dtype=np.intp), np.zeros(t.shape, dtype=bool)
        index = np.searchsorted(starts, t, side="right") - 1
        inside = (index >= 0) & (t < ends[np.maximum(index, 0)])
        return np.maximum(index, 0), inside


def renewal_events(
    rng: np.random.Generator, profile: EventProfile | None, t0: float, t1: float
) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends) in s of a renewal process inside [t0 + margin, t1 - margin]."""
    if profile is None:
        return np.empty(0), np.empty(0)
    count = int((t1 - t0) / (profile.gap_min_s + profile.duration_min_s)) + 2
    first_gap = rng.uniform(0.0, profile.gap_max_s, 1)
    gaps = np.concatenate([first_gap, rng.uniform(profile.gap_min_s, profile.gap_max_s, count - 1)])
    durations = rng.uniform(profile.duration_min_s, profile.duration_max_s, count)
    starts = t0 + CHUNK_MARGIN_S + np.cumsum(gaps) + np.concatenate([[0.0], np.cumsum(durations[:-1])])
    ends = starts + durations
    keep = ends <= t1 - CHUNK_MARGIN_S
    return starts[keep], ends[keep]


def reach_hold_knots(
    rng: np.random.Generator,
    span: tuple[float, float],
    endpoints: tuple[np.ndarray, np.ndarray],
    targets: np.ndarray,
    reach_duration: Callable[[np.ndarray, np.ndarray], np.ndarray],
    hold_s: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """Knots of hold-then-reach cycles from (t0, v0) through ``targets`` and a final reach onto (t1, v1).

    targets (M, D) must be enough to overrun the span; ``reach_duration(a, b)`` gives the duration (s,
    shape (M,)) of moves a -> b (both (M, D)). Returns times (K,) and values (K, D), both ends included.
    """
    (t0, t1), (v0, v1) = span, endpoints
    path = np.vstack([v0, targets])
    reach = reach_duration(path[:-1], path[1:])
    arrive = t0 + np.cumsum(rng.uniform(*hold_s, len(reach)) + reach)
    depart = arrive - reach
    fits = arrive + hold_s[0] + reach_duration(path[1:], np.broadcast_to(v1, targets.shape)) <= t1
    n = len(fits) if fits.all() else int(np.argmin(fits))
    times = [np.array([t0]), np.column_stack([depart[:n], arrive[:n]]).ravel()]
    values = [v0[None], np.stack([path[:n], path[1 : n + 1]], axis=1).reshape(2 * n, path.shape[1])]
    last_time, last_value = (arrive[n - 1] if n else t0), path[n]
    final_depart = t1 - reach_duration(last_value[None], v1[None])[0]
    if final_depart > last_time:
        times.append(np.array([final_depart]))
        values.append(last_value[None])
    times.append(np.array([t1]))
    values.append(v1[None])
    return np.concatenate(times), np.concatenate(values)


@dataclass(frozen=True)
class ReachStyle:
    """How a hold-and-reach process moves: random targets, move durations (s), hold durations (s)."""

    draw_targets: Callable[[np.random.Generator, int], np.ndarray]  # (rng, count) -> (count, D)
    duration: Callable[[np.ndarray, np.ndarray], np.ndarray]  # (from (M, D), to (M, D)) -> (M,) s
    hold_s: tuple[float, float]
    shortest_move_s: float

    def knots(
        self, rng: np.random.Generator, span: tuple[float, float], endpoints: tuple[np.ndarray, np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Knots (times (K,), values (K, D)) of holds and reaches filling ``span`` between ``endpoints``."""
        count = int((span[1] - span[0]) / (self.hold_s[0] + self.shortest_move_s)) + 2
        return reach_hold_knots(rng, span, endpoints, self.draw_targets(rng, count), self.duration, self.hold_s)
