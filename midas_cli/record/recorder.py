"""The recorder: creates the session, spawns one worker per device, tracks health, finalises.

Each worker appends its own streams' rows to the files this process created (record/worker.py), so the
host read -> disk path never crosses a process. Threads in the main process: the bookkeeping thread drains
the workers' bounded queue of bookkeeping messages and events into the live stats (and fsyncs every stream
file about once a second, through this process's own fds); the caller's thread polls ``snapshot()`` for
the display and decides when to ``stop()``. At stop the manifest is finalised from what is on disk.
"""

from __future__ import annotations

import logging
import os
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from midas_cli.clock import HostClock
from midas_cli.devices.base import DeviceUrl
from midas_cli.devices.registry import describe_device
from midas_cli.devices.rigconfig import check_device_name
from midas_cli.errors import ConfigError, SessionError
from midas_cli.record.foxglove_live import FoxgloveLive
from midas_cli.record.link import Inbox, StopLine
from midas_cli.record.live_model import (GESTURES_STREAM, MODEL_MODULE, RECOGNITION_DEVICE, RECOGNITION_KIND, GestureTracker,
                                         LivePlan, check_rig_streams, gestures_spec, live_stream_extra)
from midas_cli.record.lsl_out import lsl_out_manifest
from midas_cli.record.messages import DataBatch, DeviceEvent
from midas_cli.record.priority import denied_warning
from midas_cli.record.recognition import RecognitionJob, recognition_main
from midas_cli.record.stats import DeviceRecord, StreamStats, device_health, device_labels
from midas_cli.record.spawn import (reap_workers, start_worker, start_worker_server, stop_signals_blocked,
                                    warm_worker_server, worker_context)
from midas_cli.record.status import DeviceStatus, RecorderSnapshot, StreamStatus
from midas_cli.record.worker import WorkerJob, worker_main
from midas_cli.session.schema import StreamSpec
from midas_cli.session.writer import LOG_FILE, SessionMetadata, SessionWriter

log = logging.getLogger(__name__)

SYNC_EVERY_S = 1.0
STOP_GRACE_S = 5.0
STALE_RATE_S = 1.0  # no sample for this long: the live rate reads "—" rather than the old value


@dataclass
class RecordPlan:
    """What to record and where. ``devices`` maps device name -> URL."""

    metadata: SessionMetadata
    devices: dict[str, str]
    out_root: Path
    seed: int = 0
    queue_size: int = 4096
    rig: dict[str, Any] = field(default_factory=dict)
    lsl_out: bool = False  # workers also publish every stream as an LSL outlet (record/lsl_out.py)
    foxglove: str | None = None  # HOST:PORT of a live Foxglove WebSocket server (record/foxglove_live.py)
    extra_streams: tuple[StreamSpec, ...] = ()  # written by the recorder's own process (the events stream)
    priority: str = "normal"  # the device workers' priority: "high" asks for nice -10 (record/priority.py)
    live_model: LivePlan | None = None  # --live-model: gestures recognised while recording (record/recognition.py)


class Recorder:
    def __init__(self, plan: RecordPlan) -> None:
        if not plan.devices:
            raise ConfigError("nothing to record: no devices configured")
        self.plan = plan
        self.clock = HostClock.anchored_now()
        self.devices: dict[str, DeviceRecord] = {}
        self.streams: dict[str, StreamStats] = {}
        modules = self._describe_devices()
        self.gesture: GestureTracker | None = None
        if plan.live_model is not None:  # a model the rig cannot feed: refused before anything is on disk
            modules += self._add_recognition(plan.live_model)
        self._ctx = worker_context(modules)
        self._inbox = Inbox()
        self._stop_workers = StopLine(self._ctx)
        self._lock = threading.Lock()
        self._bookkeeping_done = threading.Event()
        self._processes: dict[str, Any] = {}
        self.writer: SessionWriter | None = None
        self._started_mono = 0.0
        self._rate_probe = (0.0, 0)
        self.bytes_written = 0  # stream bytes on disk: headers + what the workers reported
        self._log_handler: logging.Handler | None = None
        self.fatal_error: str | None = None
        self.live: FoxgloveLive | None = None

    def _describe_devices(self) -> list[str]:
        """Validate every URL and learn the stream layouts before anything is created on disk; the
        modules of the devices' backends (for the workers' fork server to preload)."""
        modules = []
        for name, url in self.plan.devices.items():
            check_device_name(name)
            device = describe_device(name, url, self.plan.seed)
            modules.append(type(device).__module__)
            streams = device.streams
            self.devices[name] = DeviceRecord(name, device.kind, DeviceUrl.parse(url).redacted(),
                                              device.settings(), [s.name for s in streams],
                                              labels=device_labels(device.kind, self.plan.rig.get("devices", {}).get(name)))
            for spec in streams:
                if spec.name in self.streams:
                    raise ConfigError(f"two devices produce a stream named {spec.name!r}")
                self.streams[spec.name] = StreamStats(spec)
        return modules

    def _add_recognition(self, plan: LivePlan) -> list[str]:
        """The recognition as one more worker (device ``recognition``, stream ``gestures_live``); the
        modules its process needs (preloaded by the fork server: torch is imported once)."""
        plan = self.plan.live_model = check_rig_streams(plan, {n: s.spec for n, s in self.streams.items()}, self.devices)
        spec = gestures_spec(plan)
        self.devices[RECOGNITION_DEVICE] = DeviceRecord(RECOGNITION_DEVICE, RECOGNITION_KIND, plan.run,
                                                        plan.manifest(), [spec.name])
        self.streams[spec.name] = StreamStats(spec)
        self.gesture = GestureTracker(plan.rate_hz)
        return [MODEL_MODULE, recognition_main.__module__]

    @property
    def started_monotonic_s(self) -> float:
        """``time.monotonic()`` at the session start (the manifest's start time)."""
        return self._started_mono

    def duration_reached(self, duration_s: float | None) -> bool:
        """True once ``duration_s`` has passed since the session start (never for None)."""
        return duration_s is not None and time.monotonic() >= self._started_mono + duration_s

    @property
    def path(self) -> Path:
        assert self.writer is not None, "recorder not started"
        return self.writer.folder

    def start(self) -> Path:
        """Create the session folder and every stream file (with its header), start the workers and
        the bookkeeping thread; return the folder. Elapsed time and ``--duration`` count from here.

        The stop signals are blocked while the fork server and the workers are created (never
        ignored): one that arrives meanwhile, also one sent to the whole process group, stays pending
        and reaches this process's handler as soon as they are unblocked, while each worker sets them
        to ignored before it unblocks them (it stops when told). A worker that cannot be started
        (its fork server gone) is reported as crashed; the others record and the session is finalised."""
        specs = [stats.spec for stats in self.streams.values()] + list(self.plan.extra_streams)
        if self.plan.foxglove is not None:  # a port in use is refused before anything is on disk
            self.live = FoxgloveLive(self.plan.foxglove, specs, f"midas record {self.plan.metadata.subject}")
        if self.plan.live_model is not None:  # the model's modules (torch) load before the session starts
            warm_worker_server(self._ctx)
        entries = {name: record.manifest_entry() for name, record in self.devices.items()}
        self.writer = SessionWriter.create(self.plan.out_root, self.plan.metadata, self.clock, entries, specs,
                                           self.plan.rig, extra={"lsl_out": lsl_out_manifest(self.plan.lsl_out)})
        self._started_mono = self.clock.to_monotonic_s(self.writer.manifest["start"]["host_ns"])
        self._attach_log()
        self.bytes_written = self.writer.bytes_written
        start_ns = self.writer.manifest["start"]["host_ns"]
        folder = self.path.resolve()
        start_worker_server()
        needs = self.plan.live_model.streams if self.plan.live_model is not None else {}
        feeds = {name: self._ctx.Pipe(duplex=False) for name in self.plan.devices
                 if any(s in needs for s in self.devices[name].streams)}
        with stop_signals_blocked():
            for name, url in self.plan.devices.items():
                files = {s: str(folder / self.streams[s].spec.file) for s in self.devices[name].streams}
                job = WorkerJob(name, url, self.clock.anchor_ns, start_ns, self.plan.seed,
                                stall_timeout_s=self._stall_timeout(name), parent_pid=os.getpid(),
                                session_dir=str(folder), stream_files=files, queue_size=self.plan.queue_size,
                                lsl_out=self.plan.lsl_out, kind=self.devices[name].kind, priority=self.plan.priority,
                                feed_columns={s: needs[s] for s in self.devices[name].streams if s in needs})
                self._start_worker(name, worker_main, job, self._stop_workers.reader,
                                   feeds[name][1] if name in feeds else None)
            if self.plan.live_model is not None:
                job = RecognitionJob(self.plan.live_model, self.clock.anchor_ns, os.getpid(),
                                     str(folder / self.streams[GESTURES_STREAM].spec.file), folder.name,
                                     self.plan.queue_size, self.plan.lsl_out)
                self._start_worker(RECOGNITION_DEVICE, recognition_main, job, [r for r, _ in feeds.values()])
        for pipe in feeds.values():  # the workers hold their ends: EOF then means they are gone
            for end in pipe:
                end.close()
        self._stop_workers.close_reader()
        self._bookkeeping_thread = threading.Thread(target=self._bookkeeping_loop, name="midas-bookkeeping",
                                                    daemon=True)
        self._bookkeeping_thread.start()
        log.info("recording %s with devices %s", self.writer.folder, ", ".join(self.devices))
        return self.writer.folder

    def _start_worker(self, device: str, target: Callable[..., None], job: Any, *more: Any) -> None:
        """Fork the device's worker: ``target(job, sender, *more)``. If that fails (its fork server died),
        its pipe still joins the inbox: it reads EOF at once, so the device is reported as crashed like a
        worker that died."""
        receiver, sender = self._ctx.Pipe(duplex=False)
        process = start_worker(self._ctx, f"midas-{device}", target, (job, sender, *more))
        if process is not None:
            self._processes[device] = process
        sender.close()  # the worker holds the only sending end: EOF here means it is gone
        self._inbox.add(device, receiver)

    def wait_ready(self, timeout_s: float = 15.0, should_stop: Callable[[], bool] = lambda: False,
                   on_tick: Callable[[RecorderSnapshot], None] | None = None, tick_s: float = 0.25) -> bool:
        """Wait until every device has opened or failed once, calling ``on_tick`` with the live
        snapshot meanwhile; False if ``timeout_s`` passed or ``should_stop()`` came first."""
        deadline = time.monotonic() + timeout_s
        next_tick = 0.0
        while time.monotonic() < deadline and not should_stop():
            with self._lock:
                if all(r.state not in ("starting", "opening") for r in self.devices.values()):
                    return True
            if on_tick is not None and time.monotonic() >= next_tick:
                on_tick(self.snapshot())
                next_tick = time.monotonic() + tick_s
            time.sleep(0.02)
        return False

    def starting(self) -> list[str]:
        """Devices that have neither opened nor failed yet."""
        with self._lock:
            return [name for name, r in self.devices.items() if r.state in ("starting", "opening")]

    def unopened(self) -> dict[str, str]:
        """Devices that failed every attempt to open so far: name -> their last error."""
        with self._lock:
            return {name: r.last_error for name, r in self.devices.items() if r.opens == 0 and r.state == "lost"}

    def priority_warning(self) -> str | None:
        """One line when --priority high was refused for some workers (record/priority.py), else None."""
        with self._lock:
            return denied_warning({name: r.priority for name, r in self.devices.items()})

    def _stall_timeout(self, device: str) -> float:
        """Silence that counts as a lost device: 10 periods of its slowest regular stream (at least
        0.5 s); a device with only event streams is never silent for too long."""
        rates = [s.spec.nominal_rate_hz for s in self.streams.values()
                 if s.spec.device == device and not s.spec.is_events]
        return max(0.5, 10.0 / min(rates)) if rates else float("inf")

    def _attach_log(self) -> None:
        handler = logging.FileHandler(self.path / LOG_FILE, encoding="utf-8")
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        logging.getLogger("midas_cli").addHandler(handler)
        logging.getLogger("midas_cli").setLevel(logging.INFO)
        self._log_handler = handler

    # -- bookkeeping thread -------------------------------------------------------------------
    def _bookkeeping_loop(self) -> None:
        try:
            self._drain_until_workers_exit()
        except OSError as exc:  # fsync failed (I/O error): stop cleanly, keep what is on disk
            self._fail(f"writing the session failed: {exc}")
        finally:
            self._bookkeeping_done.set()

    def _fail(self, reason: str) -> None:
        """Stop the recording because of ``reason`` (the first one given is kept)."""
        if self.fatal_error is None:
            self.fatal_error = reason
            log.error("%s; stopping the recording", reason)
        self._stop_workers.set()

    def _drain_until_workers_exit(self) -> None:
        last_sync = time.monotonic()
        exited: set[str] = set()
        while len(exited) < len(self.devices):
            for message in self._inbox.get(timeout=0.1):
                if isinstance(message, DataBatch):
                    self._account(message)
                elif isinstance(message, DeviceEvent):
                    self._on_event(message)
                    if message.event == "exited":
                        exited.add(message.device)
            for device in self._inbox.closed:  # its pipe closed without an 'exited': the process died
                if device not in exited:
                    exited.add(device)
                    self._on_event(DeviceEvent(device, "crashed", self.clock.now_ns(),
                                               "the worker process ended without saying why (killed?)"))
                    self._on_event(DeviceEvent(device, "exited", self.clock.now_ns()))
            self._inbox.closed.clear()
            if time.monotonic() - last_sync >= SYNC_EVERY_S:
                self.writer.sync()
                last_sync = time.monotonic()
            if self._stop_workers.is_set() and time.monotonic() > self._stop_deadline:
                log.error("devices %s did not stop in time", ", ".join(set(self.devices) - exited))
                return

    def _account(self, batch: DataBatch) -> None:
        """Rows a worker has already written: into the live stats (latency = its commit times)."""
        with self._lock:
            self.streams[batch.stream].add(batch, batch.committed_ns)
            self.bytes_written += batch.nbytes
            if self.gesture is not None and batch.stream == GESTURES_STREAM:
                self.gesture.update(batch.last_row)
        if self.live is not None:
            self.live.publish(self.streams[batch.stream].spec, [batch.last_row])

    def _on_event(self, event: DeviceEvent) -> None:
        with self._lock:
            record = self.devices[event.device]
            record.events.append({"t_host_ns": event.t_host_ns, "event": event.event, "message": event.message})
            if event.event == "opening":
                record.priority = event.info.get("priority") or record.priority
                if record.state == "starting":
                    record.state = "opening"
            elif event.event == "opened":
                record.opens += 1
                record.info = event.info
                record.state = "ok"
                if record.opens > 1:
                    for name in record.streams:
                        self.streams[name].reopened = True
            elif event.event in ("lost", "open_failed", "crashed"):
                record.state = "lost"
                record.last_error = (event.message.strip().splitlines() or [""])[-1]
            elif event.event == "finished":  # what the device checked at stop (e.g. OBS frames vs file)
                record.info = {**record.info, **event.info}
            elif event.event == "exited":
                record.exited = True
                record.state = "stopped"
            elif event.event == "write_failed":  # its worker exits; the whole recording stops
                self.streams[event.info["stream"]].dropped += event.info["rows"]
        level = {"lost": logging.WARNING, "open_failed": logging.WARNING, "crashed": logging.ERROR,
                 "write_failed": logging.ERROR, "warning": logging.WARNING}.get(event.event, logging.INFO)
        log.log(level, "%s: %s %s", event.device, event.event, event.message)
        if event.event == "write_failed":
            self._fail(f"writing the session failed: {event.message}")

    # -- status -------------------------------------------------------------------------------
    def snapshot(self, duration_s: float | None = None, stopping: bool = False) -> RecorderSnapshot:
        now_ns = self.clock.now_ns()
        with self._lock:
            devices = tuple(self._device_status(record, now_ns) for record in self.devices.values())
            gesture = None if self.gesture is None else self.gesture.status(now_ns)
        elapsed = time.monotonic() - self._started_mono
        return RecorderSnapshot(
            session_path=str(self.path),
            session_id=self.path.name,
            elapsed_s=elapsed,
            duration_s=duration_s,
            disk_free_bytes=shutil.disk_usage(self.path).free,
            write_rate_bps=self._write_rate(),
            bytes_written=self.bytes_written,
            devices=devices,
            stopping=stopping,
            recognising=self.gesture is not None,
            gesture=gesture,
        )

    def _write_rate(self) -> float:
        now, written = time.monotonic(), self.bytes_written
        then, before = self._rate_probe
        self._rate_probe = (now, written)
        return (written - before) / (now - then) if then and now > then else 0.0

    def _device_status(self, record: DeviceRecord, now_ns: int) -> DeviceStatus:
        streams = tuple(self._stream_status(self.streams[name], now_ns) for name in record.streams)
        return DeviceStatus(record.name, record.kind, record.url, device_health(record, streams), record.reconnects,
                            record.last_error, streams, record.labels, record.warning)

    @staticmethod
    def _stream_status(stats: StreamStats, now_ns: int) -> StreamStatus:
        age = None if stats.last_t_host_ns is None else (now_ns - stats.last_t_host_ns) / 1e9
        latest = {}
        if stats.last_row is not None:
            latest = dict(zip(stats.spec.column_names[2:], stats.last_row[2:]))
        rate = stats.measured_rate_hz() if age is not None and age < STALE_RATE_S else None
        cumulative = stats.latency_ms()
        return StreamStatus(stats.spec.name, stats.spec.nominal_rate_hz, rate, stats.samples,
                            age, stats.dropped, stats.corrupt, stats.missing_outage + stats.missing_unexplained,
                            latest, {k: cumulative[k] for k in ("p50", "p99", "max")},
                            stats.latency_window_ms(now_ns))

    # -- stopping -----------------------------------------------------------------------------
    def stop(self, status: str = "complete", reason: str = "stopped") -> dict[str, Any]:
        """Stop the workers (they write what they still had), and finalise the manifest from the
        files on disk. The session's stop time is now: what the workers still write was read by now."""
        stop_ns = self.clock.now_ns()
        self._stop_deadline = time.monotonic() + STOP_GRACE_S
        self._stop_workers.set()
        self._bookkeeping_done.wait(STOP_GRACE_S + 1.0)
        self._bookkeeping_thread.join(timeout=1.0)
        reap_workers(self._processes, self._stop_deadline + 1.0, lambda name: self.devices[name].exited)
        if self.live is not None:
            self.live.close()
        extra = {name: stats.manifest_extra() for name, stats in self.streams.items()}
        if self.plan.live_model is not None:
            live_stream_extra(self.plan.live_model, self.devices[RECOGNITION_DEVICE].info, extra[GESTURES_STREAM])
        self.writer.manifest["devices"] = {n: r.manifest_entry() for n, r in self.devices.items()}
        try:
            manifest = self.writer.finalize(status, reason, stop_ns, extra)
        except OSError as exc:
            raise SessionError(f"could not finalise {self.path}: {exc}; its stream files are kept, "
                               f"run `midas session repair {self.path}` when there is space") from exc
        log.info("session %s finalised: %s (%s)", self.path, status, reason)
        self._detach_log()
        return manifest

    def _detach_log(self) -> None:
        if self._log_handler is not None:
            logging.getLogger("midas_cli").removeHandler(self._log_handler)
            self._log_handler.close()
            self._log_handler = None

    _stop_deadline = float("inf")
