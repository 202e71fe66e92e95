"""A device worker's rows for the live gesture recognition (`midas record --live-model`): never a wait.

``RowFeed.offer`` runs in the device worker right after the rows are on disk (and published): it only
keeps the rows (a list append under a lock: the worker reads hundreds of times a second, so anything
more per read, numpy arrays included, cost it ~1 % of a core). A feeder thread, at most every
FEED_EVERY_S, takes what gathered, picks the columns the model needs as arrays and sends them to the
recognition process (record/recognition.py) in one message. When more than ``max_rows`` rows wait (the
recognition, or the pipe, is behind) further rows are the recognition's loss, counted in ``dropped``
and sent with every message: a sample is never lost, never delayed. Rows whose columns cannot be taken
(a reopened device whose columns changed, a value that is no number) are counted the same way. If the
recognition process is gone, nothing more is sent and every row offered counts as dropped.

A message is ``(batches, dropped)``: ``batches`` a list of ``(stream, t_host_ns (n,) int64, values
(n, k) float64)`` in the order the rows were written (columns in the model's order; a missing value is
NaN), ``dropped`` the running total of rows not sent.
"""

from __future__ import annotations

import threading
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from midas_cli.session.schema import StreamSpec

FEED_EVERY_S = 0.05
FEED_MAX_ROWS = 8192  # rows waiting for the feeder thread (~37 s of the EmHT at 220 Hz)
CLOSE_TIMEOUT_S = 2.0


class RowFeed:
    """The rows of the streams in ``columns`` (stream -> column names) for the recognition process."""

    def __init__(self, sender: Connection, columns: dict[str, tuple[str, ...]], max_rows: int = FEED_MAX_ROWS,
                 every_s: float = FEED_EVERY_S) -> None:
        self._sender = sender
        self.columns = columns
        self.max_rows = max_rows
        self.every_s = every_s
        self.dropped = 0
        self._index: dict[str, tuple[StreamSpec, list[int]]] = {}
        self._gone = False
        self._closing = False
        self._pending: list[tuple[StreamSpec, list[tuple]]] = []
        self._held = 0  # rows in _pending
        self._ready = threading.Condition()
        self._thread = threading.Thread(target=self._feed, name="midas-feed", daemon=True)
        self._thread.start()

    def offer(self, spec: StreamSpec, rows: list[tuple]) -> None:
        """Keep ``rows`` (seq, t_host_ns, ...) of a stream the model needs for the feeder thread, or count
        them as dropped if too many wait or the recognition is gone. Never waits, never raises: the
        worker's own recording goes on whatever happens here."""
        if spec.name not in self.columns or not rows:
            return
        with self._ready:
            if self._gone or self._held >= self.max_rows:
                self.dropped += len(rows)
                return
            self._pending.append((spec, rows))
            self._held += len(rows)
            self._ready.notify()

    def _feed(self) -> None:
        """Wait for rows, send what gathered, then wait FEED_EVERY_S; end at close or when the recognition
        is gone."""
        sent_dropped = 0
        while True:
            with self._ready:
                while not (self._pending or self._closing or self.dropped != sent_dropped):
                    self._ready.wait()
                items, self._pending, self._held = self._pending, [], 0
                closing = self._closing
            batches, failed = self._batches(items)
            with self._ready:
                self.dropped += failed
                sent_dropped = self.dropped
            if not self._send((batches, sent_dropped)) or closing:
                return
            time.sleep(self.every_s)

    def _batches(self, items: list[tuple[StreamSpec, list[tuple]]]) -> tuple[list[tuple], int]:
        """The items as (stream, times, values) arrays, one per run of items of the same stream, and how
        many rows could not be taken (a run that fails is taken item by item: only the bad ones count)."""
        runs: list[tuple[StreamSpec, list[list[tuple]]]] = []
        for spec, rows in items:
            if runs and runs[-1][0] is spec:
                runs[-1][1].append(rows)
            else:
                runs.append((spec, [rows]))
        batches, failed = [], 0
        for spec, parts in runs:
            merged = self._arrays(spec, [row for rows in parts for row in rows])
            if merged is not None:
                batches.append(merged)
                continue
            for rows in parts:
                one = self._arrays(spec, rows)
                if one is None:
                    failed += len(rows)
                else:
                    batches.append(one)
        return batches, failed

    def _arrays(self, spec: StreamSpec, rows: list[tuple]) -> tuple[str, np.ndarray, np.ndarray] | None:
        try:
            index = self._columns_of(spec, self.columns[spec.name])
            times = np.fromiter((row[1] for row in rows), dtype=np.int64, count=len(rows))
            values = np.array([[row[i] for i in index] for row in rows], dtype=np.float64)
            return spec.name, times, values.reshape(len(rows), len(index))
        except Exception:  # noqa: BLE001 - a missing column, a value that is no number: counted by the caller
            return None

    def _columns_of(self, spec: StreamSpec, columns: tuple[str, ...]) -> list[int]:
        """Where ``columns`` are in ``spec``'s rows (kept per stream while the device's spec is the same)."""
        cached = self._index.get(spec.name)
        if cached is None or cached[0] is not spec:
            cached = self._index[spec.name] = (spec, [spec.column_names.index(c) for c in columns])
        return cached[1]

    def _send(self, message: Any) -> bool:
        try:
            self._sender.send(message)
        except OSError:  # the recognition process is gone: the rows from now on are its loss
            with self._ready:
                self._gone = True
            return False
        return True

    def close(self, timeout_s: float = CLOSE_TIMEOUT_S) -> None:
        """Send what is kept and the final count (waiting up to ``timeout_s``), then close the pipe."""
        with self._ready:
            self._closing = True
            self._ready.notify()
        self._thread.join(timeout_s)
        self._sender.close()
