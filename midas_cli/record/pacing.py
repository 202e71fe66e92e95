"""How `midas record` waits: until the duration has passed or it is told to stop, showing the screen."""

from __future__ import annotations

import time
from typing import Callable

from midas_cli.record.recorder import Recorder
from midas_cli.record.status import RecorderSnapshot


def run_until(recorder: Recorder, duration_s: float | None, should_stop: Callable[[], bool],
              on_tick: Callable[[RecorderSnapshot], None], tick_s: float = 0.25) -> None:
    """Block until ``duration_s`` after the session start has passed or ``should_stop()`` is true,
    calling ``on_tick`` with a snapshot about every ``tick_s``."""
    deadline = None if duration_s is None else recorder.started_monotonic_s + duration_s
    while not should_stop():
        if recorder.duration_reached(duration_s):
            return
        on_tick(recorder.snapshot(duration_s))
        wait = tick_s if deadline is None else max(0.0, min(tick_s, deadline - time.monotonic()))
        _sleep_watching(wait, should_stop)


def _sleep_watching(seconds: float, should_stop: Callable[[], bool], step_s: float = 0.05) -> None:
    """Sleep ``seconds`` in short steps, returning early once ``should_stop()`` is true."""
    end = time.monotonic() + seconds
    while not should_stop():
        left = end - time.monotonic()
        if left <= 0:
            return
        time.sleep(min(step_s, left))
