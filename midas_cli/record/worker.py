"""A device worker process: open the device, read, batch, hand batches to the recorder.

Runs in its own process so a slow or wedged device cannot stall the others. It ignores SIGINT and
SIGHUP (the recorder decides when to stop and tells it through ``stop``), reconnects with
exponential back-off when its device fails or goes silent, and exits if the recorder disappears.
"""

from __future__ import annotations

import logging
import os
import queue
import signal
import sys
import time
import traceback
from dataclasses import dataclass

import numpy as np

from midas_cli.clock import HostClock
from midas_cli.devices.base import Device
from midas_cli.devices.registry import create_device
from midas_cli.errors import DeviceError, MidasError
from midas_cli.record.messages import DataBatch, DeviceEvent

log = logging.getLogger(__name__)

BACKOFF_START_S = 0.25
BACKOFF_MAX_S = 1.0  # a returning device is retried within 1 s (issue 3: reconnect within 2 s)


@dataclass(frozen=True)
class WorkerJob:
    """Everything a worker needs; picklable (it is sent to a spawned process)."""

    device: str
    url: str
    anchor_ns: int
    start_ns: int
    seed: int
    stall_timeout_s: float
    parent_pid: int
    session_dir: str = ""  # absolute session folder, for devices that write files into it (obs:// video/)


def run_worker(job: WorkerJob, out: "queue.Queue", stop) -> None:
    """Process entry point. A bug (any other exception) is reported to the recorder with its
    traceback as a 'crashed' event, never swallowed, and the worker exits with status 1."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    clock = HostClock(job.anchor_ns)
    totals = {"dropped": 0, "corrupt": 0}
    try:
        _serve(job, out, stop, clock, totals)
    except Exception:
        _send_event(out, job, clock, "crashed", traceback.format_exc(), totals)
        _send_event(out, job, clock, "exited", totals=totals, block=True)
        sys.exit(1)
    _send_event(out, job, clock, "exited", totals=totals, block=True)


def _serve(job: WorkerJob, out, stop, clock: HostClock, totals: dict[str, int]) -> None:
    """Open, pump, and reopen with exponential back-off until told to stop."""
    backoff = BACKOFF_START_S
    while not stop.is_set() and os.getppid() == job.parent_pid:
        try:
            device = create_device(job.device, job.url, clock, job.start_ns, job.seed, job.session_dir)
            info = device.open()
        except MidasError as exc:
            _send_event(out, job, clock, "open_failed", str(exc), totals)
            stop.wait(backoff)
            backoff = min(backoff * 2, BACKOFF_MAX_S)
            continue
        backoff = BACKOFF_START_S
        _send_event(out, job, clock, "opened", info=info, totals=totals)
        try:
            _pump(device, job, out, stop, totals)
            if device.final_info:
                _send_event(out, job, clock, "finished", info=device.final_info, totals=totals)
        except MidasError as exc:
            _send_event(out, job, clock, "lost", str(exc), totals)
        finally:
            totals["corrupt"] += device.counters.corrupt
            device.close()


def _pump(device: Device, job: WorkerJob, out, stop, totals: dict[str, int]) -> None:
    """Read until told to stop; raise DeviceError-like MidasError if the device goes silent.

    Rows are sent as soon as a read returns them: what arrived together travels together, and no
    batching window adds to the host-read -> disk latency (benchmarks/: it was the largest part)."""
    specs = {spec.name: spec for spec in device.streams}
    pending: dict[str, list[tuple]] = {name: [] for name in specs}
    last_data = time.monotonic()
    while not stop.is_set() and os.getppid() == job.parent_pid:
        rows_by_stream = device.read()
        now = time.monotonic()
        for name, rows in rows_by_stream.items():
            if rows:
                pending[name].extend(rows)
                last_data = now
        _flush(device, specs, pending, out, totals)
        if now - last_data > job.stall_timeout_s:
            _flush(device, specs, pending, out, totals)
            raise DeviceError(f"{job.device}: no data for {job.stall_timeout_s:.2f} s")
    for name, rows in device.finish().items():
        pending[name].extend(rows)
    _flush(device, specs, pending, out, totals)


def _flush(device: Device, specs, pending: dict[str, list[tuple]], out, totals: dict[str, int]) -> None:
    for name, rows in pending.items():
        if not rows:
            continue
        batch = DataBatch(
            device=device.name,
            stream=name,
            text=specs[name].format_rows(rows),
            seq=np.fromiter((r[0] for r in rows), dtype=np.int64, count=len(rows)),
            t_host_ns=np.fromiter((r[1] for r in rows), dtype=np.int64, count=len(rows)),
            last_row=rows[-1],
            dropped=totals["dropped"],
            corrupt=totals["corrupt"] + device.counters.corrupt,
        )
        try:
            out.put_nowait(batch)
        except queue.Full:
            totals["dropped"] += len(rows)
            log.error("%s: recorder queue full, %d %s samples dropped", device.name, len(rows), name)
        rows.clear()


def _send_event(out, job: WorkerJob, clock: HostClock, event: str, message: str = "",
                totals: dict[str, int] | None = None, info: dict | None = None, block: bool = False) -> None:
    totals = totals or {}
    msg = DeviceEvent(job.device, event, clock.now_ns(), message, info or {},
                      totals.get("dropped", 0), totals.get("corrupt", 0))
    try:
        out.put(msg, timeout=2.0) if block else out.put_nowait(msg)
    except queue.Full:
        log.error("%s: recorder queue full, event %s not delivered", job.device, event)
