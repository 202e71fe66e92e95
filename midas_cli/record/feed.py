"""A device worker's rows for the live gesture recognition (`midas record --live-model`): never a wait.

``RowFeed.offer`` runs in the device worker right after the rows are on disk (and published): it takes
the columns the model needs as arrays and puts them in a bounded queue without waiting. A feeder
thread sends what gathered to the recognition process (record/recognition.py) over a pipe, at most
every FEED_EVERY_S (one message instead of one per read: the per-message cost in both processes). When
the queue is full (the recognition, or the pipe, is behind) the rows are the recognition's loss,
counted in ``dropped`` and sent with every message: a sample is never lost, never delayed. If the
recognition process is gone, nothing more is sent and every row offered counts as dropped.

A message is ``(batches, dropped)``: ``batches`` a list of ``(stream, t_host_ns (n,) int64, values
(n, k) float64)`` in the order the rows were written (columns in the model's order; a missing value is
NaN), ``dropped`` the running total of rows not sent.
"""

from __future__ import annotations

import queue
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from midas_cli.session.schema import StreamSpec

FEED_EVERY_S = 0.05
FEED_QUEUE = 1024  # batches of rows (one per device read) waiting for the feeder thread
CLOSE_TIMEOUT_S = 2.0
_CLOSE = object()


class RowFeed:
    """The rows of the streams in ``columns`` (stream -> column names) for the recognition process."""

    def __init__(self, sender: Connection, columns: dict[str, tuple[str, ...]], maxsize: int = FEED_QUEUE,
                 every_s: float = FEED_EVERY_S) -> None:
        self._sender = sender
        self.columns = columns
        self.every_s = every_s
        self.dropped = 0
        self._index: dict[str, tuple[StreamSpec, list[int]]] = {}
        self._gone = False
        self._queue: queue.Queue = queue.Queue(maxsize)
        self._thread = threading.Thread(target=self._feed, name="midas-feed", daemon=True)
        self._thread.start()

    def offer(self, spec: StreamSpec, rows: list[tuple]) -> None:
        """Queue the needed columns of ``rows`` (seq, t_host_ns, ...); count them as dropped if there is
        no room, or if they cannot be taken (a reopened device whose columns changed). Never waits,
        never raises: the worker's own recording goes on whatever happens here."""
        columns = self.columns.get(spec.name)
        if columns is None or not rows:
            return
        try:
            if self._gone:
                raise BrokenPipeError("the recognition is gone")
            index = self._columns_of(spec, columns)
            times = np.fromiter((row[1] for row in rows), dtype=np.int64, count=len(rows))
            values = np.array([[row[i] for i in index] for row in rows], dtype=np.float64).reshape(len(rows), len(index))
            self._queue.put_nowait((spec.name, times, values))
        except Exception:  # noqa: BLE001 - queue.Full, a missing column, a value that is no number: counted
            self.dropped += len(rows)

    def _columns_of(self, spec: StreamSpec, columns: tuple[str, ...]) -> list[int]:
        """Where ``columns`` are in ``spec``'s rows (kept per stream while the device's spec is the same)."""
        cached = self._index.get(spec.name)
        if cached is None or cached[0] is not spec:
            cached = self._index[spec.name] = (spec, [spec.column_names.index(c) for c in columns])
        return cached[1]

    def _feed(self) -> None:
        """Send what gathered, then wait FEED_EVERY_S; end at close or when the recognition is gone."""
        while True:
            items = [self._queue.get()]
            while True:
                try:
                    items.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            closing = items[-1] is _CLOSE
            batches = [item for item in items if item is not _CLOSE]
            if not self._send((batches, self.dropped)) or closing:
                return
            time.sleep(self.every_s)

    def _send(self, message: Any) -> bool:
        try:
            self._sender.send(message)
        except OSError:  # the recognition process is gone: the rows from now on are its loss
            self._gone = True
            return False
        return True

    def close(self, timeout_s: float = CLOSE_TIMEOUT_S) -> None:
        """Send what is queued and the final count (waiting up to ``timeout_s``), then close the pipe."""
        try:
            self._queue.put(_CLOSE, timeout=timeout_s)
        except queue.Full:
            pass
        self._thread.join(timeout_s)
        self._sender.close()
