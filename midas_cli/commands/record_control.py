"""What `midas record` is told from outside its own loop: the control socket, markers, live-screen keys.

``--armed``: the session folder is created and the devices are opened and write their rows as usual
(warm-up rows are kept: nothing recorded is ever thrown away), but the recording proper starts with
`midas ctl start`: its host time goes into the manifest (``control.started_host_ns``) and the events
stream (a row ``start``, source ``ctl``), and ``--duration`` counts from it. Analysis that wants only
the recording proper cuts the streams at that time.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import asdict
from contextlib import nullcontext
from pathlib import Path
from typing import Any, Callable, Optional

from midas_cli.commands.record_keys import Keyboard, MarkerPrompt, keyboard_available
from midas_cli.console import control_line
from midas_cli.errors import ConfigError, MidasError
from midas_cli.record.control import ControlServer, default_control_path
from midas_cli.record.markers import EVENTS_DEVICE, EVENTS_STREAM, MarkerLog
from midas_cli.record.recorder import Recorder
from midas_cli.record.status import RecorderSnapshot

log = logging.getLogger(__name__)


class RemoteControl:
    """The control socket (bound at once: a path in use is refused before anything is recorded) and the
    session's markers. ``stop`` is record's stop flag (``request(reason)``, ``asked``)."""

    def __init__(self, path: Optional[Path], armed: bool, stop: Any) -> None:
        self.server = ControlServer(path if path is not None else default_control_path())
        self.armed = armed
        self.stop = stop
        self.recorder: Optional[Recorder] = None
        self.markers: Optional[MarkerLog] = None
        self.started_ns: Optional[int] = None  # host clock: the session start, or `ctl start` when armed
        self.latest: Optional[RecorderSnapshot] = None
        self.prompt = MarkerPrompt()
        self.keys = False
        self._lock = threading.Lock()

    @property
    def path(self) -> Path:
        return self.server.path

    def attach(self, recorder: Recorder) -> None:
        """The session exists: take markers and answer requests from now on."""
        self.recorder = recorder
        self.markers = MarkerLog(recorder.writer, recorder.clock, self._marker_outlet(recorder))
        if not self.armed:
            self.started_ns = recorder.writer.manifest["start"]["host_ns"]
        self.server.serve(self.handle)

    @staticmethod
    def _marker_outlet(recorder: Recorder) -> Optional[Callable[[Any, list[tuple]], None]]:
        """With --lsl-out, the markers' outlet (record/lsl_out.py), with --foxglove the live server: a
        failure is logged, recording goes on."""
        publishers: list[Callable[[Any, list[tuple]], None]] = []
        if recorder.plan.lsl_out:
            from midas_cli.record.lsl_out import LiveOutlets

            outlets = LiveOutlets(recorder.path.name, EVENTS_DEVICE, recorder.clock.anchor_ns,
                                  lambda message: log.warning("%s: %s", EVENTS_DEVICE, message))
            publishers.append(outlets.publish)
        if recorder.live is not None:
            publishers.append(recorder.live.publish)
        if not publishers:
            return None

        def publish_all(spec: Any, rows: list[tuple]) -> None:
            for publish in publishers:
                publish(spec, rows)
        return publish_all

    def watching(self, on_tick: Callable[[RecorderSnapshot], None]) -> Callable[[RecorderSnapshot], None]:
        """``on_tick`` that also keeps the latest snapshot for `ctl status`."""
        def tick(snapshot: RecorderSnapshot) -> None:
            self.latest = snapshot
            on_tick(snapshot)
        return tick

    def control_line(self) -> Any:
        """The live screen's marker line (console.control_line)."""
        markers = self.markers
        last = markers.last["text"] if markers is not None and markers.last else None
        return control_line(self.prompt.text, markers.count if markers else 0, last,
                            self.armed and self.started_ns is None, self.keys)

    def keyboard(self, live_screen: bool, on_error: Callable[[str], None]):
        """A context that reads marker keys while the live screen is on (else does nothing)."""
        if not (live_screen and keyboard_available()):
            return nullcontext()
        self.keys = True

        def add(text: str) -> None:
            try:
                self.add_marker(text, "key")
            except MidasError as exc:
                on_error(f"midas: marker not written: {exc}")
        return Keyboard(self.prompt, add)

    def add_marker(self, text: str, source: str) -> dict[str, Any]:
        if self.markers is None:
            raise ConfigError("the session is not created yet; try again in a moment")
        return self.markers.add(text, source)

    def wait_for_start(self, should_stop: Callable[[], bool], on_tick: Callable[[RecorderSnapshot], None],
                       duration_s: Optional[float]) -> Optional[float]:
        """Armed: block until `ctl start` (or a stop); return ``duration_s`` counted from the session start."""
        assert self.recorder is not None
        while self.started_ns is None and not should_stop():
            on_tick(self.recorder.snapshot(None))
            time.sleep(0.1)
        if duration_s is None or self.started_ns is None:
            return duration_s
        return duration_s + (self.started_ns - self.recorder.writer.manifest["start"]["host_ns"]) / 1e9

    def finish(self, reason: str) -> str:
        """No more markers (before the recorder takes its stop time); the manifest's ``control`` entry;
        the stop reason, saying so when an armed recording never started."""
        if self.markers is not None:
            self.markers.close()
        if self.recorder is not None and self.recorder.writer is not None:
            manifest = self.recorder.writer.manifest
            manifest["control"] = {"socket": str(self.path), "armed": self.armed, "started_host_ns": self.started_ns}
            # a marker that could not be written was refused to whoever sent it, never acknowledged
            manifest["streams"][EVENTS_STREAM].update(dropped=0, corrupt=0)
        if self.armed and self.started_ns is None:
            return f"{reason}; armed, `midas ctl start` never came"
        return reason

    def close(self) -> None:
        self.server.close()

    # -- requests (the server's thread) ------------------------------------------------------------
    def handle(self, request: dict[str, Any]) -> dict[str, Any]:
        command = request.get("cmd")
        if command == "status":
            return self.status()
        if command == "mark":
            source = request.get("source", "ctl")
            if source not in ("mark", "ctl"):
                raise ConfigError(f"a remote marker's source is mark or ctl, got {source!r}")
            return {"marker": self.add_marker(str(request.get("text", "")), source), **self._where()}
        if command == "start":
            return self._start()
        if command == "stop":
            self.stop.request("stopped by `midas ctl stop`")
            return {"state": "stopping", **self._where()}
        raise ConfigError(f"unknown command {command!r}: expected start, stop, status or mark")

    def _start(self) -> dict[str, Any]:
        with self._lock:
            if not self.armed:
                raise ConfigError("the recording is already running (start is for `midas record --armed`)")
            if self.started_ns is not None:
                raise ConfigError("the recording was already started")
            if self.stop.asked:
                raise ConfigError("the recording is stopping")
            row = self.add_marker("start", "ctl")
            self.started_ns = row["t_host_ns"]
        return {"state": "recording", "started_host_ns": self.started_ns, **self._where()}

    def state(self) -> str:
        if self.stop.asked or (self.latest is not None and self.latest.stopping):
            return "stopping"
        return "armed" if self.armed and self.started_ns is None else "recording"

    def status(self) -> dict[str, Any]:
        snapshot = self.latest
        devices = {d.name: {"kind": d.kind, "health": d.state, "reconnects": d.reconnects,
                            "last_error": d.last_error} for d in (snapshot.devices if snapshot else ())}
        health = {state: sum(1 for d in devices.values() if d["health"] == state)
                  for state in sorted({d["health"] for d in devices.values()})}
        recorder = self.recorder
        now_ns = recorder.clock.now_ns() if recorder is not None else None
        markers = self.markers
        return {**self._where(), "state": self.state(), "armed": self.armed,
                "elapsed_s": None if snapshot is None else round(snapshot.elapsed_s, 3),
                "duration_s": None if self.started_ns is None or now_ns is None
                else round((now_ns - self.started_ns) / 1e9, 3),
                "limit_s": None if snapshot is None else snapshot.duration_s,
                "health": health, "devices": devices, "markers": markers.count if markers else 0,
                **({"gesture": _gesture(snapshot)} if snapshot is not None and snapshot.recognising else {})}

    def _where(self) -> dict[str, Any]:
        path = self.recorder.path if self.recorder is not None and self.recorder.writer is not None else None
        return {"session_path": None if path is None else str(path), "pid": os.getpid()}


def _gesture(snapshot: RecorderSnapshot) -> dict[str, Any] | None:
    """`ctl status`'s ``gesture`` (with --live-model): label, probability, duration_s, latency_ms, age_s;
    None before the first frame was predicted."""
    return None if snapshot.gesture is None else asdict(snapshot.gesture)
