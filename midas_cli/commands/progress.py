"""The one progress display every long command uses: rich's live bar when stderr is a terminal, and
otherwise (SLURM, nohup, cron, a pipe) a plain line per task every ``MIDAS_PROGRESS_INTERVAL_S``
seconds (default 10) saying what, how far and the ETA -- a log file shows the run is alive.

Both displays take the same calls (``add_task``, ``update``, ``advance``: the subset of
``rich.progress.Progress`` the commands use), so a command is written once.
"""

from __future__ import annotations

import math
import os
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator

from rich.progress import BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn, TimeRemainingColumn

from midas_cli.commands.common import err, error_line
from midas_cli.console import clock_text
from midas_cli.errors import ConfigError

INTERVAL_ENV = "MIDAS_PROGRESS_INTERVAL_S"
DEFAULT_INTERVAL_S = 10.0
DEFAULT_COLUMNS = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())


@dataclass
class _Task:
    description: str
    total: float | None
    started: float
    completed: float = 0.0
    last_line: float | None = None
    fields: dict[str, Any] = field(default_factory=dict)


class PlainProgress:
    """Progress as plain stderr lines: one per task at most every ``interval_s`` seconds (0: on every
    update), and one when a task reaches its total. ``clock`` is monotonic seconds."""

    def __init__(self, interval_s: float, clock: Callable[[], float] = time.monotonic,
                 write: Callable[[str], None] = error_line) -> None:
        self.interval_s, self._clock, self._write = interval_s, clock, write
        self._tasks: list[_Task] = []

    def __enter__(self) -> PlainProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def add_task(self, description: str, total: float | None = None, **fields: Any) -> int:
        self._tasks.append(_Task(description, total, self._clock(), fields=fields))
        return len(self._tasks) - 1

    def advance(self, task_id: int, advance: float = 1) -> None:
        self.update(task_id, advance=advance)

    def update(self, task_id: int, *, total: float | None = None, completed: float | None = None,
               advance: float | None = None, description: str | None = None, **fields: Any) -> None:
        """Like ``rich.progress.Progress.update``: a None argument leaves that value as it was."""
        task = self._tasks[task_id]
        restarted = completed is not None and completed < task.completed  # e.g. the next ablation run's epochs
        task.total = task.total if total is None else total
        task.completed = completed if completed is not None else task.completed + (advance or 0)
        task.description = description or task.description
        task.fields.update(fields)
        now = self._clock()
        if restarted:
            task.started = now
        finished = task.total is not None and task.completed >= task.total
        if finished or task.last_line is None or now - task.last_line >= self.interval_s:
            task.last_line = now
            self._write(progress_line(task.description, task.completed, task.total, now - task.started,
                                      " ".join(str(v) for v in task.fields.values() if v not in ("", None))))


def progress_line(what: str, done: float, total: float | None, elapsed_s: float, info: str = "") -> str:
    """``midas: progress: what: done/total (pct%), elapsed HH:MM:SS, ETA HH:MM:SS[, info]``; the ETA
    extrapolates the rate so far and is 'unknown' before the first step or without a total."""
    if total:
        how_far = f"{done:g}/{total:g} ({100 * done / total:.0f}%)"
        eta = clock_text(elapsed_s * (total - done) / done) if done > 0 else "unknown"
    else:
        how_far, eta = f"{done:g} done", "unknown"
    tail = f", {info}" if info else ""
    return f"midas: progress: {what}: {how_far}, elapsed {clock_text(elapsed_s)}, ETA {eta}{tail}"


def progress_interval_s() -> float:
    """Seconds between plain progress lines, from ``MIDAS_PROGRESS_INTERVAL_S`` (default 10)."""
    text = os.environ.get(INTERVAL_ENV, "").strip()
    if not text:
        return DEFAULT_INTERVAL_S
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        raise ConfigError(f"{INTERVAL_ENV} must be a number of seconds >= 0, got {text!r}")
    return value


def stderr_is_terminal() -> bool:
    return sys.stderr.isatty() and os.environ.get("TERM", "") != "dumb"


@contextmanager
def progress_display(*columns: ProgressColumn, transient: bool = False) -> Iterator[Progress | PlainProgress]:
    """The display for a long command: rich ``columns`` (default: what, bar, n/total, ETA) in a
    terminal, plain progress lines otherwise."""
    if not stderr_is_terminal():
        yield PlainProgress(progress_interval_s())
        return
    with Progress(*(columns or DEFAULT_COLUMNS), console=err, transient=transient) as progress:
        yield progress
