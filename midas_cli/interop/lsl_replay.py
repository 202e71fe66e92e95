"""Play a recorded session back as live LSL streams (`midas replay --to lsl`), like ``ros2 bag play``.

Every chosen stream becomes one outlet (devices/lsl/outlet.py: name, device kind as type, channel
labels and units, nominal rate, ``source_id`` ``midas:<session>:<stream>``). The streams are read a
piece at a time (``Session.iter_stream``) and merged in ``t_host_ns`` order, so memory stays flat in
the session's length.

Times. ``t0`` is the first ``t_host_ns`` of the chosen streams; a sample's *play time* is
``v = (t_host_ns - t0) / 1e9`` s, plus ``pass * cycle_s`` on the ``pass``-th repetition of ``--loop``
(``cycle_s`` = the recorded span + one period of the fastest stream, so a pass follows the previous one
as the next sample would have). With ``start`` = the LSL clock when playing begins:

* the sample is pushed when ``local_clock() >= start + v / speed``;
* its LSL timestamp is ``start + v``: the recorded time shifted onto the local LSL clock, so a receiver
  sees exactly the recorded spacing, at any speed (at speed 1 the timestamps are the push times; at
  speed 2 they run ahead of the local clock by half the play time, as ros2 bag play keeps its
  messages' own stamps). The timestamps are computed, never read off the clock, so a late push (a busy
  machine) shows as latency, not as jitter.
"""

from __future__ import annotations

import heapq
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from midas_cli.devices.lsl.device import import_pylsl
from midas_cli.devices.lsl.outlet import channel_columns, open_outlet, source_id, stream_type
from midas_cli.errors import ConfigError, SessionError
from midas_cli.interop.common import device_kind
from midas_cli.session.reader import Session
from midas_cli.session.schema import StreamSpec

WAIT_STEP_S = 0.05  # how often a wait looks at should_stop
PROGRESS_EVERY_S = 0.25
EVENTS_GAP_S = 0.1  # gap between --loop passes when every chosen stream is an event stream


@dataclass(frozen=True)
class ReplayStream:
    """One stream to publish: its spec, its device's kind and its first/last host times (ns; None when
    it has no rows)."""

    spec: StreamSpec
    kind: str
    first_ns: int | None
    last_ns: int | None
    samples: int


@dataclass
class ReplayPlan:
    """A checked replay: which streams, how fast, whether to loop."""

    session: Session
    streams: list[ReplayStream]
    speed: float = 1.0
    loop: bool = False
    delay_s: float = 1.0  # outlets are announced this long before the first sample (consumers connect)

    @property
    def name(self) -> str:
        return str(self.session.manifest.get("session_id") or self.session.path.name)

    @property
    def t0_ns(self) -> int:
        return min(s.first_ns for s in self.streams if s.first_ns is not None)

    @property
    def samples_per_pass(self) -> int:
        return sum(s.samples for s in self.streams)

    @property
    def max_wait_s(self) -> float:
        """The longest one wait for a sample may last (s): the session's plausible span
        (``Session.plausible_host_ns``) at this speed, a bound that holds whatever the files say."""
        low, high = self.session.plausible_host_ns()
        return (self.cycle_s if high is None else (high - low) / 1e9) / self.speed

    @property
    def cycle_s(self) -> float:
        """Play time from one pass's start to the next's (see the module docstring)."""
        span = (max(s.last_ns for s in self.streams if s.last_ns is not None) - self.t0_ns) / 1e9
        rates = [s.spec.nominal_rate_hz for s in self.streams if s.spec.nominal_rate_hz]
        return span + (1.0 / max(rates) if rates else EVENTS_GAP_S)


@dataclass
class ReplayResult:
    """What was sent: samples per stream, passes started, and whether ``should_stop`` ended it."""

    samples: dict[str, int] = field(default_factory=dict)
    passes: int = 0
    stopped: bool = False

    @property
    def total(self) -> int:
        return sum(self.samples.values())


def plan_replay(path: Path | str, streams: Sequence[str] = (), speed: float = 1.0, loop: bool = False,
                delay_s: float = 1.0) -> ReplayPlan:
    """Open the session and check the request: ``streams`` (empty: all) must exist, ``speed`` be a
    finite number > 0 and ``delay_s`` >= 0 (ConfigError), the chosen streams must hold rows
    (SessionError); a session still being recorded is refused (SessionError)."""
    if not (math.isfinite(speed) and speed > 0):
        raise ConfigError(f"--speed must be a finite number > 0, got {speed}")
    if not (math.isfinite(delay_s) and delay_s >= 0):
        raise ConfigError(f"--delay must be a finite number of seconds >= 0, got {delay_s}")
    session = Session.open(path)
    if session.status == "recording":
        raise SessionError(f"{session.path} is still marked 'recording': replay a finished session "
                           f"(or run `midas session repair {session.path}`)")
    names = list(dict.fromkeys(streams)) or session.stream_names
    unknown = [n for n in names if n not in session.stream_names]
    if unknown:
        raise ConfigError(f"--streams: {', '.join(unknown)} not in {session.path.name} "
                          f"(streams: {', '.join(session.stream_names) or 'none'})")
    chosen = [_replay_stream(session, name) for name in names]
    if not any(s.samples for s in chosen):
        raise SessionError(f"{session.path.name}: the chosen streams ({', '.join(names)}) hold no rows to replay")
    bounds = session.plausible_host_ns()
    for stream in chosen:
        for t_ns in (stream.first_ns, stream.last_ns):
            if t_ns is not None:
                check_plausible(session, stream.spec, t_ns, bounds)
    return ReplayPlan(session, chosen, speed, loop, delay_s)


def check_plausible(session: Session, spec: StreamSpec, t_ns: int, bounds: tuple[int, int | None]) -> None:
    """SessionError when ``t_ns`` (a sample's host time) is outside ``bounds``
    (``session.plausible_host_ns()``): playing it would wait that long (years, for a damaged value)."""
    low, high = bounds
    if t_ns < low or (high is not None and t_ns > high):
        raise SessionError(f"{session.path}: {spec.file} holds t_host_ns {t_ns}, far outside the session's time "
                           f"span: not replayed (`midas session verify {session.path}` names the line)")


def _replay_stream(session: Session, name: str) -> ReplayStream:
    """The stream's first/last host time and rows: from the manifest, else read once."""
    spec = session.stream_spec(name)
    entry = session.manifest["streams"][name]
    kind = device_kind(session, name)
    first, last, count = entry.get("first_t_host_ns"), entry.get("last_t_host_ns"), entry.get("samples")
    if not (isinstance(first, int) and isinstance(last, int) and isinstance(count, int)):
        first, last, count = None, None, 0
        for chunk in session.iter_stream(name):
            times = chunk["t_host_ns"].to_numpy(np.int64)
            if len(times):
                first = int(times.min()) if first is None else min(first, int(times.min()))
                last = int(times.max()) if last is None else max(last, int(times.max()))
                count += len(times)
    return ReplayStream(spec, kind, first if count else None, last if count else None, count)


def _samples(session: Session, index: int, spec: StreamSpec) -> Iterator[tuple[int, int, list[float]]]:
    """(t_host_ns, index, channel values) of every row of the stream, in file order."""
    names = [c.name for c in channel_columns(spec)]
    for chunk in session.iter_stream(spec.name):
        times = chunk["t_host_ns"].to_numpy(np.int64).tolist()
        if spec.has_text:  # a string outlet (outlet.channel_format): each value as its CSV text, missing ""
            values = chunk[names].astype("string").fillna("").to_numpy(dtype=object).tolist()
        else:
            values = chunk[names].to_numpy(dtype=np.float64, na_value=np.nan).tolist()
        for t, row in zip(times, values):
            yield t, index, row


def replay(plan: ReplayPlan, should_stop: Callable[[], bool] = lambda: False,
           on_progress: Callable[[ReplayResult], None] | None = None) -> ReplayResult:
    """Publish the plan's streams and play them (once, or until ``should_stop()`` with ``loop``).
    ``on_progress`` gets the running result about every PROGRESS_EVERY_S and at each pass's end."""
    pylsl = import_pylsl()
    clock = pylsl.local_clock
    outlets = [open_outlet(s.spec, s.kind, plan.name) for s in plan.streams]
    result = ReplayResult({s.spec.name: 0 for s in plan.streams})
    try:
        if not _wait_until(clock() + plan.delay_s, clock, should_stop):
            result.stopped = True
            return result
        start, t0, last_report = clock(), plan.t0_ns, 0.0
        bounds, max_wait_s = plan.session.plausible_host_ns(), plan.max_wait_s
        while not result.stopped and (result.passes == 0 or plan.loop):
            offset_s = result.passes * plan.cycle_s
            result.passes += 1
            merged = heapq.merge(*(_samples(plan.session, i, s.spec) for i, s in enumerate(plan.streams)))
            for t_ns, index, values in merged:
                check_plausible(plan.session, plan.streams[index].spec, t_ns, bounds)  # the file, not the manifest
                play_s = offset_s + (t_ns - t0) / 1e9
                if not _wait_until(min(start + play_s / plan.speed, clock() + max_wait_s), clock, should_stop):
                    result.stopped = True
                    break
                outlets[index].push_sample(values, start + play_s)
                result.samples[plan.streams[index].spec.name] += 1
                if on_progress is not None and time.monotonic() - last_report >= PROGRESS_EVERY_S:
                    last_report = time.monotonic()
                    on_progress(result)
            if on_progress is not None:
                on_progress(result)
    finally:
        outlets.clear()  # pylsl closes an outlet when its object goes
    return result


def _wait_until(when_s: float, clock: Callable[[], float], should_stop: Callable[[], bool]) -> bool:
    """Sleep until ``clock() >= when_s``; False (at once) if ``should_stop()`` comes first."""
    while True:
        if should_stop():
            return False
        left = when_s - clock()
        if left <= 0:
            return True
        time.sleep(min(left, WAIT_STEP_S))


def describe(plan: ReplayPlan) -> list[dict[str, Any]]:
    """One entry per published stream: what a consumer resolves it by and what it carries."""
    return [{"name": s.spec.name, "type": stream_type(s.spec, s.kind), "source_id": source_id(plan.name, s.spec.name),
             "channels": len(channel_columns(s.spec)), "nominal_srate": s.spec.nominal_rate_hz or 0.0,
             "samples": s.samples} for s in plan.streams]
