"""Recorder <-> worker plumbing over plain pipes: bookkeeping messages up, the stop request down.

``multiprocessing.Queue`` and ``Event`` are built on named POSIX semaphores (``/dev/shm/sem.mp-*``)
that only a clean exit unlinks: every SIGKILL of the process group left eight behind. Pipes are
file descriptors, so the kernel closes them with the processes and nothing can leak. They also say
when a worker is gone (its end reads EOF) and when the recorder is gone (the stop line reads EOF).

Worker side: ``WorkerLink`` has the ``queue.Queue`` interface the worker uses (``put_nowait``
raises ``queue.Full``; ``put`` waits), backed by a bounded in-process queue and a feeder thread that
sends to the pipe, so a slow recorder never blocks a device read. ``StopSignal`` has the
``Event`` interface the worker uses (``is_set``, ``wait``).
"""

from __future__ import annotations

import queue
import threading
from multiprocessing.connection import Connection, wait
from typing import Any

_CLOSE = object()
CLOSE_TIMEOUT_S = 5.0


class StopLine:
    """The recorder's stop request: ``set()`` writes a byte the workers' ends become readable with.

    Every worker polls the same pipe and never reads it, so one byte reaches them all; if the
    recorder dies, its end closes and the workers' ends read EOF, which counts as a stop too."""

    def __init__(self, context) -> None:
        self.reader, self._writer = context.Pipe(duplex=False)
        self._set = False

    def set(self) -> None:
        if not self._set:
            self._set = True
            try:
                self._writer.send_bytes(b"s")
            except OSError:  # no worker left to tell
                pass

    def is_set(self) -> bool:
        return self._set

    def close_reader(self) -> None:
        """Drop the recorder's copy of the workers' end once they have theirs."""
        self.reader.close()


class StopSignal:
    """A worker's view of the stop line (``threading.Event``'s is_set/wait)."""

    def __init__(self, reader: Connection) -> None:
        self._reader = reader

    def is_set(self) -> bool:
        return self._reader.poll(0)

    def wait(self, timeout: float) -> bool:
        return self._reader.poll(timeout)


class WorkerLink:
    """A worker's outgoing messages: a bounded queue drained into the pipe by a feeder thread."""

    def __init__(self, sender: Connection, maxsize: int) -> None:
        self._sender = sender
        self._queue: queue.Queue = queue.Queue(maxsize)
        self._feeder = threading.Thread(target=self._feed, name="midas-link", daemon=True)
        self._feeder.start()

    def put_nowait(self, message: Any) -> None:
        self._queue.put_nowait(message)

    def put(self, message: Any, timeout: float | None = None) -> None:
        self._queue.put(message, timeout=timeout)

    def _feed(self) -> None:
        while True:
            message = self._queue.get()
            if message is _CLOSE:
                return
            try:
                self._sender.send(message)
            except OSError:  # the recorder is gone: nobody to tell any more
                return

    def close(self, timeout_s: float = CLOSE_TIMEOUT_S) -> None:
        """Send what is queued (waiting up to ``timeout_s``), then close the pipe."""
        try:
            self._queue.put(_CLOSE, timeout=timeout_s)
        except queue.Full:
            pass
        self._feeder.join(timeout_s)
        self._sender.close()


class Inbox:
    """The recorder's side: the messages of every worker, as they arrive; a worker whose pipe
    reads EOF (it exited, or died) is reported once through ``closed``."""

    def __init__(self) -> None:
        self._receivers: dict[Connection, str] = {}
        self.closed: list[str] = []

    def add(self, device: str, receiver: Connection) -> None:
        self._receivers[receiver] = device

    def get(self, timeout: float) -> list[Any]:
        """Messages that arrived within ``timeout`` s (every ready pipe's next message)."""
        if not self._receivers:
            return []
        messages = []
        for receiver in wait(list(self._receivers), timeout):
            try:
                messages.append(receiver.recv())
            except (EOFError, OSError):
                self.closed.append(self._receivers.pop(receiver))
                receiver.close()
        return messages

    @property
    def open_devices(self) -> list[str]:
        return list(self._receivers.values())
