"""The local executor: units in this process (``jobs`` = 1) or in ``jobs`` worker processes."""

from __future__ import annotations

import logging
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence

from midas_cli.jobs.rundir import RunDir
from midas_cli.jobs.runner import TaskFn, run_unit

log = logging.getLogger(__name__)


def _run_quietly(run_dir: RunDir, index: int, fn: TaskFn) -> bool:
    """Run a unit in a worker; False when it failed (it is marked failed with its error)."""
    try:
        run_unit(run_dir, index, fn)
    except Exception:  # marked failed by run_unit; the other units go on
        return False
    return True


def run_local(run_dir: RunDir, indices: Sequence[int], fn: TaskFn, jobs: int = 1,
              on_unit: Callable[[int, bool], None] | None = None, **extra: Any) -> None:
    """Run ``indices`` of ``run_dir``; ``on_unit(index, ok)`` after each. ``extra`` keyword arguments go
    to ``fn`` when the units run in this process (a progress callback), not to worker processes."""
    if jobs == 1 or len(indices) <= 1:
        for k in indices:
            try:
                run_unit(run_dir, k, fn, **extra)
                ok = True
            except Exception:
                ok = False
            if on_unit:
                on_unit(k, ok)
        return
    # spawn, not fork: a forked copy of a process that has started threads (torch, the align readers) can
    # deadlock; each worker imports what it needs once and runs several units
    context = multiprocessing.get_context("spawn")
    workers = min(jobs, len(indices))
    with _threads_per_worker(workers):
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=context)
        try:
            futures = {pool.submit(_run_quietly, run_dir, k, fn): k for k in indices}
            for future in as_completed(futures):
                ok = future.result()
                if on_unit:
                    on_unit(futures[future], ok)
        except BaseException:
            # a stop signal (SystemExit from __main__'s handler: `kill PID` reaches this process alone) or
            # an error: the workers stop now, not when their units end (leaving the pool's `with` waits for
            # them: minutes of training); their units stay unfinished and run again next time
            _stop_workers(pool)
            raise
        pool.shutdown(wait=True)


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Terminate ``pool``'s worker processes (SIGTERM), wait briefly for them, drop the queued units."""
    processes = list((getattr(pool, "_processes", None) or {}).values())  # no public way before Python 3.14
    for process in processes:
        if process.is_alive():
            process.terminate()
    for process in processes:
        process.join(timeout=5)
    pool.shutdown(wait=False, cancel_futures=True)


@contextmanager
def _threads_per_worker(workers: int) -> Iterator[None]:
    """OMP_NUM_THREADS for the workers spawned meanwhile (numpy, torch, OpenCV read it at import): the
    CPUs shared out, so N workers do not each start a thread per CPU. A value already set is kept."""
    if "OMP_NUM_THREADS" in os.environ:
        yield
        return
    os.environ["OMP_NUM_THREADS"] = str(max(1, (os.cpu_count() or 1) // workers))
    try:
        yield
    finally:
        del os.environ["OMP_NUM_THREADS"]
