"""How the recorder starts and ends its worker processes: a fork server with the worker module
preloaded, started with the stop signals blocked (never ignored), so that a Ctrl-C or hang-up sent to
the whole process group at that instant cannot kill it (or the workers it forks) and still reaches the
recorder afterwards; at the end every worker is waited for, and killed if it does not end."""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import signal
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from multiprocessing import forkserver, resource_tracker
from typing import Any

from midas_cli.processes import process_alive

log = logging.getLogger(__name__)

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
WORKER_MODULE = "midas_cli.record.worker"


def worker_context(backend_modules: Iterable[str] = ()):
    """Workers are forked by multiprocessing's fork server, which imports the worker module and the
    ``backend_modules`` (those of the devices to record; a backend is imported only when needed,
    devices/registry.py) once: each worker then starts in milliseconds instead of importing numpy and
    its backend again, as a spawned one would (~0.5 s of CPU each). The server is itself a fresh,
    single-threaded process (forking the recorder, which may hold threads of pylsl or BLAS, would not
    be safe). ``start_worker_server`` starts it; it keeps the stop signals blocked for life, and every
    worker it forks inherits the block."""
    context = mp.get_context("forkserver")
    context.set_forkserver_preload([WORKER_MODULE, *sorted(set(backend_modules))])
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


def warm_worker_server(context: Any) -> None:
    """Start the fork server and wait until it has imported what it preloads (it forks one trivial
    process once that is done): `record --live-model` preloads torch, seconds of imports that would
    otherwise delay every device's first sample after the session's start."""
    start_worker_server()
    with stop_signals_blocked():
        process = context.Process(target=int, name="midas-warm-up", daemon=True)
        process.start()
    process.join()


@contextlib.contextmanager
def stop_signals_blocked() -> Iterator[None]:
    """Block SIGINT/SIGTERM/SIGHUP in this thread for the duration (pending ones are delivered when
    the block ends, never dropped); children started meanwhile inherit the block."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def start_worker(context: Any, name: str, target: Callable[..., None], args: tuple) -> Any | None:
    """Start a daemon worker process through ``context`` (its fork server); None, logged, if the fork
    server could not fork it (it died: the recorder goes on without this worker)."""
    process = context.Process(target=target, args=args, name=name, daemon=True)
    try:
        process.start()
    except (OSError, EOFError) as exc:
        log.error("%s: could not start the worker process: %s", name, exc or type(exc).__name__)
        return None
    return process


def reap_workers(processes: Mapping[str, Any], deadline: float, said_exited: Callable[[str], bool]) -> None:
    """Wait for every worker process (by device) to end. One that said 'exited' has closed its files
    and is only tearing its interpreter down: on a busy machine that can take a while, so it gets until
    ``deadline`` (monotonic) and is then killed quietly. One that never said 'exited' is an error.
    SIGKILL, not SIGTERM: workers ignore every stop signal, and one that writes its own rows must be
    gone before the files are hashed."""
    for device, process in processes.items():
        if wait_gone(process, deadline):
            continue
        level = logging.INFO if said_exited(device) else logging.ERROR
        log.log(level, "worker %s %s; killing it", process.name,
                "is slow to exit after it finished" if said_exited(device) else "did not exit")
        process.kill()
        wait_gone(process, time.monotonic() + 2.0)


def wait_gone(process: Any, deadline: float, step_s: float = 0.02) -> bool:
    """Wait until the worker ``process`` has ended or ``deadline`` (monotonic) passed; True if it ended.
    Its own PID decides: the fork server that reports a worker's end may itself be gone."""
    process.join(timeout=max(0.0, deadline - time.monotonic()))
    while process_alive(process.pid) and time.monotonic() < deadline:
        time.sleep(step_s)
    return not process_alive(process.pid)
