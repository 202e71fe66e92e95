"""How the recorder starts its workers: a fork server with the worker module preloaded, and the stop
signals blocked (never ignored) while it starts, so a Ctrl-C or hang-up at that instant is delivered
afterwards instead of killing the server under running workers or being lost."""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import signal
from typing import Iterator

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
WORKER_MODULE = "midas_cli.record.worker"


def worker_context():
    """Workers are forked by multiprocessing's fork server, which imports the worker module (and
    through it every device backend) once: each worker then starts in milliseconds instead of
    importing numpy and the backends again, as a spawned one would (~0.5 s of CPU each). The server
    is itself a fresh, single-threaded process (forking the recorder, which may hold threads of
    pylsl or BLAS, would not be safe). It is started inside ``stop_signals_blocked`` and keeps the
    stop signals blocked: a terminal's Ctrl-C or hang-up cannot kill it under running workers."""
    context = mp.get_context("forkserver")
    context.set_forkserver_preload([WORKER_MODULE])
    return context


@contextlib.contextmanager
def stop_signals_blocked() -> Iterator[None]:
    """Block SIGINT/SIGTERM/SIGHUP in this thread for the duration (pending ones are delivered when
    the block ends, never dropped); children started meanwhile inherit the block."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
