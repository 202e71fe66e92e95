"""A device worker process: open the device, read, append the rows to the session, tell the recorder.

Runs in its own process so a slow or wedged device cannot stall the others. Right after each read it
formats the rows and appends them to its streams' files itself (the recorder created them, with
their headers): no second process stands between a device read and the disk. The recorder gets
bookkeeping only (sequence numbers, times, bytes) and fsyncs the files about once a second, so a
worker never blocks on fsync.

It ignores SIGINT, SIGTERM and SIGHUP, also those a terminal or ``kill -- -PGID`` sends to the whole
process group: the recorder decides when to stop and tells it through ``stop`` (or SIGKILLs a worker
that does not stop), and it starts with them blocked, so none can reach it before it ignores them. It
reconnects with exponential back-off when its device fails or goes silent, and exits if the recorder
disappears. Messages go through a pipe (``record/link.py``): nothing a SIGKILL could leave behind. A
failed write (disk full, file too large) ends the worker with a ``write_failed`` event: the recorder
then stops the whole recording and keeps what is on disk.
"""

from __future__ import annotations

import gc
import logging
import queue
import signal
import sys
import time
import traceback
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.clock import HostClock
from midas_cli.devices.base import Device
from midas_cli.devices.registry import DeviceContext, create_device
from midas_cli.errors import DeviceError, MidasError
from midas_cli.processes import process_alive
from midas_cli.record.feed import RowFeed
from midas_cli.record.link import StopSignal, WorkerLink
from midas_cli.record.lsl_out import LiveOutlets
from midas_cli.record.messages import DataBatch, DeviceEvent
from midas_cli.record.priority import apply_priority
from midas_cli.session.schema import StreamSpec
from midas_cli.session.writer import StreamAppender

log = logging.getLogger(__name__)

BACKOFF_START_S = 0.25
BACKOFF_MAX_S = 1.0  # a returning device is retried within 1 s (issue 3: reconnect within 2 s)
EVENT_TIMEOUT_S = 2.0  # how long an event waits for room in the queue
BOOKKEEPING_EVERY_S = 0.05  # rows already on disk are reported to the recorder at most this often
ALIVE_EVERY_S = 0.25  # how often the pump checks that the recorder still exists


@dataclass(frozen=True)
class WorkerJob:
    """Everything a worker needs; picklable (it is sent to a spawned process)."""

    device: str
    url: str
    anchor_ns: int
    start_ns: int
    seed: int
    stall_timeout_s: float
    parent_pid: int  # the recorder's process id (a worker's parent is the fork server)
    session_dir: str = ""  # absolute session folder, for devices that write files into it (obs:// video/)
    stream_files: dict[str, str] = field(default_factory=dict)  # stream -> absolute path; the recorder created it
    queue_size: int = 4096  # bookkeeping messages held before they are merged (a slow recorder)
    lsl_out: bool = False  # also publish the rows as LSL outlets (record/lsl_out.py)
    kind: str = ""  # the device's kind (the outlets' LSL type)
    priority: str = "normal"  # "high": nice -10 where permitted (record/priority.py)
    feed_columns: dict[str, tuple[str, ...]] = field(default_factory=dict)  # --live-model: stream -> its columns


class StreamWriteFailed(Exception):
    """Appending to (or opening) a stream file failed: the recording cannot go on."""

    def __init__(self, stream: str, rows: int, error: OSError) -> None:
        super().__init__(f"stream {stream}: {error}")
        self.stream, self.rows = stream, rows


class PendingRows:
    """Bookkeeping of one stream's rows written since the last message (plain lists: cheap to extend)."""

    def __init__(self) -> None:
        self.seq: list[int] = []
        self.t_host_ns: list[int] = []
        self.committed_ns: list[int] = []
        self.last_row: tuple = ()
        self.nbytes = self.write_ns = self.corrupt = 0

    def add(self, rows: list[tuple], committed: int, nbytes: int, write_ns: int, corrupt: int) -> None:
        self.seq.extend(r[0] for r in rows)
        self.t_host_ns.extend(r[1] for r in rows)
        self.committed_ns.extend([committed] * len(rows))
        self.last_row, self.corrupt = rows[-1], corrupt
        self.nbytes += nbytes
        self.write_ns += write_ns

    def batch(self, device: str, stream: str) -> DataBatch:
        return DataBatch(device, stream, np.array(self.seq, dtype=np.int64), np.array(self.t_host_ns, dtype=np.int64),
                         np.array(self.committed_ns, dtype=np.int64), self.last_row, self.nbytes, self.write_ns,
                         self.corrupt)


class WorkerOutput:
    """Where a worker's rows go: appended to their stream files, then accounted to the recorder.

    The rows are on disk before the recorder hears of them, so the bookkeeping may come later: it is
    gathered per stream and sent at most every BOOKKEEPING_EVERY_S (one message per stream then,
    instead of one per read: at 850 reads a second the per-message cost, a thread hand-off, a pickle
    and a pipe write in the worker and the same back in the recorder, was most of the recording's
    CPU). A full queue can only delay it further: a message it refuses is held and merged into that
    stream's next message, never dropped. Events send everything gathered or held first, so the
    recorder sees them in order."""

    def __init__(self, device: str, out: "queue.Queue", clock: HostClock,
                 every_s: float = BOOKKEEPING_EVERY_S) -> None:
        self.device, self.out, self.clock = device, out, clock
        self.appenders: dict[str, StreamAppender] = {}
        self.held: dict[str, DataBatch] = {}
        self.pending: dict[str, PendingRows] = {}
        self.every_ns = int(every_s * 1e9)
        self.last_sent_ns = 0
        self.corrupt_closed = 0  # corrupt records counted by earlier connections (counters restart per open)
        self.outlets: LiveOutlets | None = None  # --lsl-out: rows are published after they are on disk
        self.feed: RowFeed | None = None  # --live-model: the recognition's rows, offered last (record/feed.py)

    def open(self, files: dict[str, str]) -> None:
        """Open the existing stream files for appending (never creates one)."""
        for stream, path in files.items():
            try:
                self.appenders[stream] = StreamAppender(Path(path))
            except OSError as exc:
                raise StreamWriteFailed(stream, 0, exc) from exc

    def write(self, spec: StreamSpec, rows: list[tuple], corrupt: int) -> None:
        """Append ``rows`` (seq, t_host_ns, ...) to the stream's file, then send their bookkeeping."""
        text = spec.format_rows(rows)
        started = self.clock.now_ns()
        try:
            nbytes = self.appenders[spec.name].append(text)
        except OSError as exc:
            raise StreamWriteFailed(spec.name, len(rows), exc) from exc
        committed = self.clock.now_ns()
        pending = self.pending.get(spec.name)
        if pending is None:
            pending = self.pending[spec.name] = PendingRows()
        pending.add(rows, committed, nbytes, committed - started, corrupt)
        if self.outlets is not None:  # published once on disk; the bookkeeping may follow later
            self.outlets.publish(spec, rows)
        if self.feed is not None:
            self.feed.offer(spec, rows)
        self.tick(committed)

    def tick(self, now_ns: int | None = None) -> None:
        """Send the gathered bookkeeping if BOOKKEEPING_EVERY_S has passed since the last time."""
        now_ns = self.clock.now_ns() if now_ns is None else now_ns
        if self.pending and now_ns - self.last_sent_ns >= self.every_ns:
            self.send_pending()
            self.last_sent_ns = now_ns

    def send_pending(self) -> None:
        for stream, pending in self.pending.items():
            self.send(pending.batch(self.device, stream))
        self.pending.clear()

    def send(self, batch: DataBatch) -> None:
        """Queue ``batch`` without waiting; if the queue is full, hold it (merged with what is held)."""
        held = self.held.pop(batch.stream, None)
        if held is not None:
            batch = held.merged(batch)
        try:
            self.out.put_nowait(batch)
        except queue.Full:
            self.held[batch.stream] = batch

    def event(self, event: str, message: str = "", info: dict[str, Any] | None = None) -> None:
        """Send a device event after any gathered or held bookkeeping (waits up to EVENT_TIMEOUT_S for room)."""
        self.send_pending()
        for stream in list(self.held):
            self._put_waiting(self.held.pop(stream))
        self._put_waiting(DeviceEvent(self.device, event, self.clock.now_ns(), message, info or {}))

    def _put_waiting(self, message: DataBatch | DeviceEvent) -> None:
        try:
            self.out.put(message, timeout=EVENT_TIMEOUT_S)
        except queue.Full:
            if isinstance(message, DataBatch):  # keep it for the next message of its stream
                self.held[message.stream] = message
                return
            log.error("%s: recorder queue full for %.0f s, %s not delivered", self.device, EVENT_TIMEOUT_S,
                      getattr(message, "event", "bookkeeping"))

    def close(self) -> None:
        if self.outlets is not None:
            self.outlets.close()
        if self.feed is not None:
            self.feed.close()
        for appender in self.appenders.values():
            appender.close()


def ignore_stop_signals() -> None:
    """A worker ignores the stop signals (they arrive blocked, see ``Recorder.start``): the recorder
    tells it when to stop."""
    stop_signals = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    for signum in stop_signals:
        signal.signal(signum, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, stop_signals)


def freeze_inherited_objects() -> None:
    """Put every object the process inherited from the fork server (numpy, the device backends and, with
    ``--live-model``, torch: a hundred thousand objects and more) out of the cyclic collector's reach. A
    worker allocates rows all the time, so collections run often, and each full one walked them all
    again (touching their pages too, which copies them from the fork server's). ``gc.freeze`` is O(1)."""
    gc.freeze()


def worker_main(job: WorkerJob, sender: Connection, stop_reader: Connection,
                feed_sender: Connection | None = None) -> None:
    """Entry point of the worker process: the signals first, then its priority (before any thread
    starts: threads inherit it), then the pipes (``feed_sender``: rows for the live recognition), then
    ``run_worker``."""
    ignore_stop_signals()
    freeze_inherited_objects()
    priority = apply_priority(job.priority)
    link = WorkerLink(sender, job.queue_size)
    feed = None if feed_sender is None else RowFeed(feed_sender, job.feed_columns)
    try:
        run_worker(job, link, StopSignal(stop_reader), priority, feed)
    finally:
        link.close()


def run_worker(job: WorkerJob, out: "queue.Queue", stop, priority: dict[str, Any] | None = None,
               feed: RowFeed | None = None) -> None:
    """Process entry point; ``priority`` (what ``apply_priority`` put in force) goes with the 'opening'
    event; ``feed`` gets the rows once they are on disk. A failed write is reported as a 'write_failed' event (the worker then
    exits normally); a bug (any other exception) as a 'crashed' event with its traceback, never
    swallowed, and the worker exits with status 1."""
    output = WorkerOutput(job.device, out, HostClock(job.anchor_ns))
    output.feed = feed
    status = 0
    try:
        output.event("opening", info={"priority": priority} if priority else None)
        output.open(job.stream_files)
        if job.lsl_out:
            output.outlets = LiveOutlets(Path(job.session_dir).name, job.kind, job.anchor_ns,
                                         lambda message: output.event("warning", message))
        _serve(job, output, stop)
    except StreamWriteFailed as exc:
        output.event("write_failed", str(exc), {"stream": exc.stream, "rows": exc.rows})
    except Exception:
        output.event("crashed", traceback.format_exc())
        status = 1
    output.event("exited")
    output.close()
    if status:
        sys.exit(status)


def _serve(job: WorkerJob, output: WorkerOutput, stop) -> None:
    """Open, pump, and reopen with exponential back-off until told to stop."""
    backoff = BACKOFF_START_S
    context = DeviceContext(output.clock, job.start_ns, job.seed, job.session_dir)  # one per worker: kept over reopens
    while not stop.is_set() and process_alive(job.parent_pid):
        try:
            device = create_device(job.device, job.url, context)
            info = device.open()
        except MidasError as exc:
            output.event("open_failed", str(exc))
            stop.wait(backoff)
            backoff = min(backoff * 2, BACKOFF_MAX_S)
            continue
        backoff = BACKOFF_START_S
        output.event("opened", info=info)
        try:
            _pump(device, job, output, stop)
            if device.final_info:
                output.event("finished", info=device.final_info)
        except MidasError as exc:
            output.event("lost", str(exc))
        finally:
            output.corrupt_closed += device.counters.corrupt
            device.close()


def _pump(device: Device, job: WorkerJob, output: WorkerOutput, stop) -> None:
    """Read until told to stop; raise DeviceError if the device goes silent.

    Rows are written as soon as a read returns them: what arrived together is written together, and
    no batching window or process hop adds to the host-read -> disk latency (see benchmarks/)."""
    specs = {spec.name: spec for spec in device.streams}
    last_data = checked_alive = time.monotonic()
    while not stop.is_set():
        rows_by_stream = device.read()
        now = time.monotonic()
        if any(rows_by_stream.values()):
            last_data = now
            _flush(device, specs, rows_by_stream, output)
        else:
            output.tick()
        if now - last_data > job.stall_timeout_s:
            raise DeviceError(f"{job.device}: no data for {job.stall_timeout_s:.2f} s")
        if now - checked_alive >= ALIVE_EVERY_S:
            if not process_alive(job.parent_pid):
                break
            checked_alive = now
    _flush(device, specs, device.finish(), output)


def _flush(device: Device, specs: dict[str, StreamSpec], rows_by_stream: dict[str, list[tuple]],
           output: WorkerOutput) -> None:
    """Write each stream's new rows (in the order the device returned the streams)."""
    corrupt = output.corrupt_closed + device.counters.corrupt
    for name, rows in rows_by_stream.items():
        if rows:
            output.write(specs[name], rows, corrupt)
