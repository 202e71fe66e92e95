"""``obs://HOST:PORT?fps=30&marker=SOURCE``: OBS Studio records the session's video over obs-websocket v5.

Opening connects (password from the environment, see ``connection``), checks OBS's frame rate against
``fps``, points the recording at the session's ``video/`` folder as MKV, starts it and waits for the
RecordStateChanged STARTED event, whose host time anchors the frame clock (``frames``).

The ``<name>`` stream has one row per encoded frame: seq (frame index, from 0 across the session's
OBS files), t_host_ns (STARTED + i / fps) and t_device_s (i / fps, the recording timecode). Rows are
written live, about every ``poll`` s, for the frames GetRecordStatus says OBS has handed to the muxer,
so a crash loses at most the last poll's frames. At a normal stop the recording is stopped (STOPPED
event), the finished file is read with ffprobe, the rows of the last frames are added, and the check
(file frames vs rows, frames off the i/fps grid, OBS's skipped/lagged counters) goes into the
device's manifest info under ``recording`` with status ``ok`` or ``mismatch``.

If the connection is lost the worker reopens the device: a recording OBS is still making into this
session is stopped and a new file started; its frames continue the seq numbering after the frames of
the session's earlier files, so the frames never recorded as rows show as a sequence gap (outage); the sync
marker is not resumed after a reconnect (its toggle numbering would restart).
"""

from __future__ import annotations

import logging
import os
import time
from fractions import Fraction
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from midas_cli.clock import HostClock
from midas_cli.devices.base import Device, DeviceUrl
from midas_cli.devices.obs.connection import ObsConnection, resolve_password
from midas_cli.devices.obs.frames import FrameClock, check_recording, count_existing_frames, probe_frame_times
from midas_cli.devices.obs.marker import MarkerPlan, SyncMarker
from midas_cli.devices.obs.profile import RecordTarget
from midas_cli.errors import ConfigError, DeviceError
from midas_cli.session.schema import SEQ, Column, StreamSpec

log = logging.getLogger(__name__)

PARAMS = {"fps": float, "timeout": float, "poll": float, "password_env": str, "marker": str,
          "marker_scene": str, "marker_at": float, "marker_on": float, "marker_every": float}
DEFAULTS = {"fps": 30.0, "timeout": 5.0, "poll": 0.1, "password_env": "", "marker": "", "marker_scene": "",
            "marker_at": 1.0, "marker_on": 0.5, "marker_every": 0.0}
DEFAULT_PORT = 4455
STARTED = "OBS_WEBSOCKET_OUTPUT_STARTED"
STOPPED = "OBS_WEBSOCKET_OUTPUT_STOPPED"
START_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = 3.0
MAX_SLEEP_S = 0.01
FPS_TOLERANCE_HZ = 0.01


class ObsDevice(Device):
    """OBS Studio's record output as the session's video and frame clock."""

    kind = "video"

    def __init__(self, name: str, url: DeviceUrl, clock: HostClock, session_dir: str = "") -> None:
        super().__init__(name, url)
        _refuse_password_in_url(url)
        self.params = url.take(PARAMS, DEFAULTS)
        self.host, self.port = _address(url)
        _check_params(url, self.params)
        self.marker_plan = None
        if self.params["marker"]:
            p = self.params
            self.marker_plan = MarkerPlan(p["marker"], p["marker_scene"], p["marker_at"], p["marker_on"],
                                          p["marker_every"])
        self.clock = clock
        self.session_dir = Path(session_dir) if session_dir else None
        self.connection: ObsConnection | None = None
        self.target: RecordTarget | None = None
        self.marker: SyncMarker | None = None
        self.frames: FrameClock | None = None
        self._reset_recording()

    def _reset_recording(self) -> None:
        self.output_file: Path | None = None
        self._seq_base = 0
        self._next_frame = 0
        self._next_poll = 0.0
        self._counters_at_start: dict[str, int] = {}

    @property
    def streams(self) -> list[StreamSpec]:
        columns = (SEQ, Column("t_host_ns", "int", "ns", clock="host",
                               description="frame time on the host clock: RecordStateChanged STARTED + t_device_s"),
                   Column("t_device_s", "float", "s", 6, clock="device", description="recording timecode, i / fps"))
        specs = [StreamSpec(self.name, self.name, columns, self.params["fps"],
                            "OBS video frame times, one row per encoded frame (reference clock for align)")]
        if self.marker_plan is not None:
            specs.append(self.marker_plan.spec(self.name))
        return specs

    def settings(self) -> dict[str, Any]:
        return {**self.params, "container": "mkv", "record_folder": "video"}

    # -- open -----------------------------------------------------------------------------------
    def open(self) -> dict[str, Any]:
        if self.session_dir is None:
            raise DeviceError(f"{self.name}: obs:// records into a session folder; use it through `midas record`")
        password, password_from = resolve_password(self.params["password_env"])
        self.connection = ObsConnection(self.host, self.port, password, self.params["timeout"], self.clock)
        try:
            return {**self._start_recording(), "password_from": password_from}
        except Exception:
            self.close()
            raise

    def _start_recording(self) -> dict[str, Any]:
        conn = self.connection
        version = conn.request("GetVersion")
        video = conn.request("GetVideoSettings")
        fps = self._checked_fps(video)
        folder = (self.session_dir / "video").resolve()
        self._stop_leftover_recording(folder)
        self._reset_recording()
        earlier_files = sorted(folder.glob(f"{self.name}_*.mkv"))
        self._seq_base = count_existing_frames(earlier_files)
        self.target = RecordTarget(conn)
        mode = self.target.point_at(folder, self.name)
        if self.marker_plan is not None and not earlier_files:  # after a reconnect its seq would restart
            self.marker = SyncMarker(self.marker_plan, conn, self.clock)
        self._counters_at_start = self._obs_counters()
        request_ns = self.clock.now_ns()
        conn.request("StartRecord")
        ack_ns = self.clock.now_ns()
        started = conn.wait_for(STARTED, START_TIMEOUT_S)
        self.frames = FrameClock(fps, started.t_host_ns)
        self.output_file = Path(started.output_path) if started.output_path else None
        if self.marker is not None:
            self.marker.started_ns = started.t_host_ns
        log.info("%s: OBS %s recording at %s fps into %s", self.name, version.get("obsVersion"), fps, folder)
        return {"model": f"OBS Studio {version.get('obsVersion')}", "obs_version": version.get("obsVersion"),
                "websocket_version": version.get("obsWebSocketVersion"), "fps": f"{fps.numerator}/{fps.denominator}",
                "resolution": f"{video['outputWidth']}x{video['outputHeight']}", "output_mode": mode,
                "file": self._relative(self.output_file), "seq_base": self._seq_base,
                "start_request_host_ns": request_ns, "start_ack_host_ns": ack_ns,
                "started_host_ns": started.t_host_ns, **self._marker_info()}

    def _checked_fps(self, video: dict[str, Any]) -> Fraction:
        fps = Fraction(int(video["fpsNumerator"]), int(video["fpsDenominator"]))
        if abs(float(fps) - self.params["fps"]) > FPS_TOLERANCE_HZ:
            raise DeviceError(f"{self.name}: OBS renders at {float(fps):.3f} fps ({fps}) but the URL expects "
                              f"fps={self.params['fps']:g}: put ?fps={float(fps):.3f} in the URL or change OBS's "
                              f"Settings > Video > Common FPS Values")
        return fps

    def _stop_leftover_recording(self, folder: Path) -> None:
        """A recording already running into this session (a reconnect) is finished; any other refuses."""
        if not self.connection.request("GetRecordStatus").get("outputActive"):
            return
        current = self.connection.request("GetRecordDirectory").get("recordDirectory", "")
        if not current or Path(current).resolve() != folder:
            raise DeviceError(f"{self.name}: OBS is already recording (into {current or 'its own folder'}): stop "
                              f"that recording in OBS first, midas starts its own in the session's video/")
        log.warning("%s: OBS was still recording this session after a reconnect; starting a new file", self.name)
        self.connection.request("StopRecord")
        self.connection.wait_for(STOPPED, STOP_TIMEOUT_S)

    def _marker_info(self) -> dict[str, Any]:
        if self.marker is None:
            return {}
        return {"marker": {"scene": self.marker.scene, "source": self.marker.plan.source,
                           "scene_item_id": self.marker.item_id, "stream": f"{self.name}_marker"}}

    # -- recording ------------------------------------------------------------------------------
    def read(self) -> dict[str, list[tuple]]:
        if self.frames is None or self.connection is None:
            raise DeviceError(f"{self.name}: read before open")
        rows: dict[str, list[tuple]] = {}
        if self.marker is not None:
            rows[f"{self.name}_marker"] = self.marker.poll()
        now = time.monotonic()
        if now < self._next_poll:
            time.sleep(min(self._next_poll - now, MAX_SLEEP_S))
            return rows
        self._next_poll = now + self.params["poll"]
        rows[self.name] = self._new_frame_rows()
        return rows

    def _new_frame_rows(self) -> list[tuple]:
        status = self.connection.request("GetRecordStatus")
        if not status.get("outputActive"):
            raise DeviceError(f"{self.name}: OBS is no longer recording (stopped in OBS, or disk full?)")
        if status.get("outputPaused"):
            raise DeviceError(f"{self.name}: the OBS recording was paused; midas needs a continuous recording "
                              f"(it starts a new file when the device reopens)")
        available = self.frames.frames_in(int(status["outputDuration"]))
        rows = self.frames.rows(self._next_frame, available, self._seq_base)
        self._next_frame = max(self._next_frame, available)
        return rows

    def _obs_counters(self) -> dict[str, int]:
        stats = self.connection.request("GetStats")
        return {"output_skipped_frames": int(stats.get("outputSkippedFrames", 0)),
                "render_lagged_frames": int(stats.get("renderSkippedFrames", 0))}

    # -- stop -----------------------------------------------------------------------------------
    def finish(self) -> dict[str, list[tuple]]:
        """Stop OBS's recording, check the file, and return the rows of its last frames."""
        if self.frames is None or self.connection is None:
            return {}
        rows_live = self._next_frame
        counters = {k: v - self._counters_at_start.get(k, 0) for k, v in self._obs_counters().items()}
        stop_request_ns = self.clock.now_ns()
        path = self.connection.request("StopRecord").get("outputPath")
        stopped = self.connection.wait_for(STOPPED, STOP_TIMEOUT_S)
        self.output_file = Path(stopped.output_path or path or self.output_file)
        times = probe_frame_times(self.output_file)
        check = check_recording(times, self.frames.fps, rows_live, counters)
        for problem in check.problems + check.warnings:
            log.warning("%s: %s", self.name, problem)
        self.final_info = {"recording": {"file": self._relative(self.output_file),
                                         "started_host_ns": self.frames.started_ns,
                                         "stop_request_host_ns": stop_request_ns,
                                         "stopped_host_ns": stopped.t_host_ns, **check.to_manifest()}}
        rows = {self.name: self.frames.rows(rows_live, len(times), self._seq_base)}
        self._next_frame = max(rows_live, len(times))
        self.frames = None
        return rows

    def close(self) -> None:
        if self.connection is None:
            return
        for restore in (self.marker.restore if self.marker else None, self.target.restore if self.target else None):
            if restore is not None:
                try:
                    restore()
                except DeviceError as exc:
                    log.warning("%s: could not restore OBS settings: %s", self.name, exc)
        self.marker = self.target = None
        self.connection.close()
        self.connection = None

    def _relative(self, path: Path | None) -> str | None:
        if path is None:
            return None
        return os.path.relpath(path, self.session_dir.resolve())


def _refuse_password_in_url(url: DeviceUrl) -> None:
    if urlsplit(url.raw).password is not None or "password" in url.params:
        raise ConfigError(f"{url.redacted()}: a password in the URL ends up in shell history, process lists and "
                          f"logs; put it in an environment variable (MIDAS_OBS_PASSWORD, or the one named by "
                          f"password_env in the rig) instead")


def _address(url: DeviceUrl) -> tuple[str, int]:
    parts = urlsplit(url.raw)
    try:
        port = parts.port or DEFAULT_PORT
    except ValueError:
        raise ConfigError(f"{url.raw}: the port is not a number (expected obs://HOST:PORT)") from None
    if parts.path not in ("", "/"):
        raise ConfigError(f"{url.raw}: unexpected path {parts.path!r} (expected obs://HOST:PORT?options)")
    return parts.hostname or "localhost", port


def _check_params(url: DeviceUrl, params: dict[str, Any]) -> None:
    if not 0 < params["fps"] <= 240:
        raise ConfigError(f"{url.raw}: fps must be in (0, 240], got {params['fps']}")
    if params["timeout"] <= 0:
        raise ConfigError(f"{url.raw}: timeout must be positive seconds, got {params['timeout']}")
    if not 0 < params["poll"] <= 1:
        raise ConfigError(f"{url.raw}: poll must be in (0, 1] s, got {params['poll']}")
