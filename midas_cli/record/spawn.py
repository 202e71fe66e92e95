"""How the recorder starts its workers: a fork server with the worker module preloaded, started with
the stop signals blocked (never ignored), so that a Ctrl-C or hang-up sent to the whole process group
at that instant cannot kill it (or the workers it forks) and still reaches the recorder afterwards."""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import signal
from multiprocessing import forkserver, resource_tracker
from typing import Iterator

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
WORKER_MODULE = "midas_cli.record.worker"


def worker_context():
    """Workers are forked by multiprocessing's fork server, which imports the worker module (and
    through it every device backend) once: each worker then starts in milliseconds instead of
    importing numpy and the backends again, as a spawned one would (~0.5 s of CPU each). The server
    is itself a fresh, single-threaded process (forking the recorder, which may hold threads of
    pylsl or BLAS, would not be safe). ``start_worker_server`` starts it; it keeps the stop signals
    blocked for life, and every worker it forks inherits the block."""
    context = mp.get_context("forkserver")
    context.set_forkserver_preload([WORKER_MODULE])
    return context


def start_worker_server() -> None:
    """Start multiprocessing's helper processes with every stop signal blocked: first the resource
    tracker (the fork server needs one), then the fork server. Nothing if both already run.

    Two blocks, not one: CPython's resource tracker start blocks SIGINT and SIGTERM around its own
    spawn and then *unblocks* them (it does not restore the caller's mask). Started inside the fork
    server's start, it left the fork server to be spawned with them unblocked, and a Ctrl-C to the
    process group killed it while it imported the worker module (the recorder then failed with
    ``Aborted.`` and left the session ``recording``). A signal that arrives between the two blocks
    simply reaches the recorder's handler."""
    with stop_signals_blocked():
        resource_tracker.ensure_running()  # it ignores SIGINT/SIGTERM; SIGHUP stays blocked in it
    with stop_signals_blocked():
        forkserver.ensure_running()


@contextlib.contextmanager
def stop_signals_blocked() -> Iterator[None]:
    """Block SIGINT/SIGTERM/SIGHUP in this thread for the duration (pending ones are delivered when
    the block ends, never dropped); children started meanwhile inherit the block."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
