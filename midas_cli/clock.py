"""The host clock shared by every process of a recording (DESIGN.md section 4).

Timestamps are Unix-epoch nanoseconds derived from CLOCK_MONOTONIC plus an anchor taken once per
session, so they never jump when NTP steps the wall clock. Worker processes receive the anchor and
compute identical times from the same kernel monotonic clock.
"""

from __future__ import annotations

import time
from dataclasses import dataclass


@dataclass(frozen=True)
class HostClock:
    """`now_ns()` = CLOCK_MONOTONIC + `anchor_ns`, in Unix-epoch nanoseconds."""

    anchor_ns: int

    @classmethod
    def anchored_now(cls) -> "HostClock":
        """Anchor the monotonic clock to the wall clock once (take the tightest of a few tries)."""
        best: tuple[int, int] | None = None
        for _ in range(5):
            m0 = time.monotonic_ns()
            wall = time.time_ns()
            m1 = time.monotonic_ns()
            if best is None or m1 - m0 < best[0]:
                best = (m1 - m0, wall - (m0 + m1) // 2)
        assert best is not None
        return cls(anchor_ns=best[1])

    def now_ns(self) -> int:
        return time.monotonic_ns() + self.anchor_ns

    def from_monotonic_ns(self, monotonic_ns: int) -> int:
        return monotonic_ns + self.anchor_ns

    def to_monotonic_s(self, host_ns: int) -> float:
        """Host time -> `time.monotonic()` seconds, for sleeping until a host time."""
        return (host_ns - self.anchor_ns) / 1e9
