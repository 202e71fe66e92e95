"""`midas ARGS` run in the test's own process (the property tests draw hundreds of inputs: a process
start each would cost minutes), with an alarm that turns a hang into a result instead of a stuck suite."""

from __future__ import annotations

import contextlib
import io
import os
import signal
import sys
from typing import Callable, TextIO


class Hung(BaseException):
    """Raised by the alarm inside a run that did not finish in time (a BaseException: midas's own
    `except Exception` handlers must not take it for an internal error)."""


def run_in_process(args: list[str], out: TextIO, err: TextIO, hang_s: int, env: dict[str, str] | None = None,
                   on_hang: Callable[[], None] | None = None) -> int | None:
    """Run the `midas` entry point with ``args``, its stdout into ``out``, its stderr (and the library
    warnings midas prints there) into ``err``, ``env`` set for the run only: the exit code, or None when
    it hung for ``hang_s`` seconds (``on_hang`` is then called, e.g. to unblock a reader)."""
    from midas_cli.commands.common import STDERR_LOG
    from midas_cli.commands.main import run

    def _alarm(_signum, _frame):
        raise Hung()

    env = env or {}
    saved_env = {k: os.environ.get(k) for k in env}
    argv, previous = sys.argv, signal.signal(signal.SIGALRM, _alarm)
    sys.argv = ["midas", *args]
    os.environ.update(env)
    log_stream = STDERR_LOG.setStream(err)
    code: int | None
    try:
        signal.alarm(hang_s)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            run()
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except Hung:
        code = None
        if on_hang is not None:
            on_hang()
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
        sys.argv = argv
        STDERR_LOG.setStream(log_stream)
        _restore(saved_env)
    return code


def _restore(saved: dict[str, str | None]) -> None:
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


def captured(args: list[str], hang_s: int, env: dict[str, str] | None = None,
             on_hang: Callable[[], None] | None = None) -> tuple[int | None, str, str]:
    """``run_in_process`` into fresh buffers: (exit code or None, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    code = run_in_process(args, out, err, hang_s, env, on_hang)
    return code, out.getvalue(), err.getvalue()
