"""``obs://HOST:PORT?fps=30&marker=SOURCE``: OBS Studio records the session's video over obs-websocket v5.

Opening connects (password from the environment or a password file, see ``connection``), checks OBS's frame rate against
``fps``, saves the operator's OBS settings on disk (``saved``) and points the recording at the
session's ``video/`` folder as MKV (``profile``), starts it and waits for the RecordStateChanged
STARTED event, whose host time anchors the frame clock (``frames``), and for OBS's first frame.

The ``<name>`` stream has one row per encoded frame: seq, t_host_ns (STARTED + i / fps), t_device_s
(i / fps, the recording timecode) and segment (which of the session's files holds the frame, from 0).
Rows are written live, about every ``poll`` s, for the frames GetRecordStatus says OBS has handed to
the muxer, so a crash loses at most the last poll's frames. At a normal stop the recording is stopped
(STOPPED event), every segment file of the session is read with ffprobe, the rows of the last file's
last frames are added, and the check of each segment (file frames vs rows written for it, frames off
the i/fps grid, OBS's skipped/lagged counters) goes into the device's manifest info under
``recording`` with status ``ok`` or ``mismatch``.

If the connection is lost (OBS killed, crashed or restarted, or the network dropped) the worker reopens
the device: a recording OBS is still making into this session is stopped and a new segment file is
started. Its frame 0 gets the seq of its STARTED time on the frame grid of the session's first frame
(and always more than any seq written), so the frames the outage cost show as a sequence gap of their
number, which the recorder explains as an outage. Rows written live for frames a killed OBS never put
in its file stay in the stream and are reported per segment. The sync marker is not resumed after a
reconnect (its toggle numbering would restart). OBS's own settings are put back on every way out, from
the saved copy (see ``profile``).
"""

from __future__ import annotations

import logging
import os
import time
from fractions import Fraction
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from midas_cli.devices.base import Device, DeviceContext, DeviceUrl
from midas_cli.devices.obs.connection import ObsConnection, resolve_password
from midas_cli.devices.obs.frames import (FrameClock, RecordingCheck, WrittenRows, check_recording, probe_frame_times,
                                          segment_files, unreadable_recording)
from midas_cli.devices.obs.marker import MarkerPlan, SyncMarker
from midas_cli.devices.obs.profile import (STARTED, STOPPED, RecordTarget, recover_stale, restore_settings,
                                           segment_file_prefix, stop_orphan_recording)
from midas_cli.devices.obs.saved import SavedSettings, SettingsStore
from midas_cli.errors import ConfigError, DeviceError
from midas_cli.session.schema import Column, StreamSpec

log = logging.getLogger(__name__)

PARAMS = {"fps": float, "timeout": float, "poll": float, "password_env": str, "password_file": str, "marker": str,
          "marker_scene": str, "marker_at": float, "marker_on": float, "marker_every": float}
DEFAULTS = {"fps": 30.0, "timeout": 5.0, "poll": 0.1, "password_env": "", "password_file": "", "marker": "",
            "marker_scene": "",
            "marker_at": 1.0, "marker_on": 0.5, "marker_every": 0.0}
DEFAULT_PORT = 4455
START_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = 3.0
MAX_SLEEP_S = 0.01
FPS_TOLERANCE_HZ = 0.01


class ObsDevice(Device):
    """OBS Studio's record output as the session's video and frame clock."""

    kind = "video"

    def __init__(self, name: str, url: DeviceUrl, context: DeviceContext) -> None:
        super().__init__(name, url)
        self.params = url.take(PARAMS, DEFAULTS)
        self.host, self.port = _address(url)
        _check_params(url, self.params)
        self.marker_plan = None
        if self.params["marker"]:
            p = self.params
            self.marker_plan = MarkerPlan(p["marker"], p["marker_scene"], p["marker_at"], p["marker_on"],
                                          p["marker_every"])
        self.clock = context.clock
        self.session_dir = Path(context.session_dir) if context.session_dir else None
        self.connection: ObsConnection | None = None
        self.store = SettingsStore(self.host, self.port)
        self.saved: SavedSettings | None = None  # the operator's settings, as saved on disk
        self.marker: SyncMarker | None = None
        self.frames: FrameClock | None = None
        self.output_file: Path | None = None
        self._next_frame = 0
        self._next_poll = 0.0
        self._counters_at_start: dict[str, int] = {}

    @property
    def streams(self) -> list[StreamSpec]:
        columns = (Column("seq", "int", "count", description="frame number in the session: frame i of segment k "
                          "is seq_base(k) + i, seq_base on the frame grid of segment 0's first frame, so frames "
                          "lost between segments leave a gap of their number; only grows"),
                   Column("t_host_ns", "int", "ns", clock="host",
                          description="frame time on the host clock: the segment's RecordStateChanged STARTED + "
                                      "t_device_s"),
                   Column("t_device_s", "float", "s", 6, clock="device",
                          description="recording timecode in the segment's file, i / fps (frame index i = "
                                      "t_device_s x fps)"),
                   Column("segment", "int", "index", description="the session's OBS recording file that holds "
                          "the frame: video/<device>_s<segment>_<date>_<time>.mkv, from 0; a new segment starts "
                          "each time midas reconnects to OBS"))
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
        password, password_from = resolve_password(self.params["password_env"], self.params["password_file"])
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
        restored = recover_stale(conn, self.store)  # a copy a killed midas left: put back, say so
        if restored:
            log.warning("%s: %s", self.name, restored)
        self._stop_leftover_recording(folder)
        written = WrittenRows.read(self._stream_file(), fps)
        segment = written.next_segment(segment_files(folder, self.name))
        target = RecordTarget(conn)
        mode, values = target.plan(folder, segment_file_prefix(self.name, segment))
        if self.marker_plan is not None and segment == 0:  # after a reconnect its seq would restart
            self.marker = SyncMarker(self.marker_plan, conn, self.clock)
        self._save_operator_settings(target, values, folder)
        target.apply(values)
        if self.marker is not None:
            self.marker.hide()
        self._counters_at_start = self._obs_counters()
        request_ns = self.clock.now_ns()
        conn.request("StartRecord")
        ack_ns = self.clock.now_ns()
        started = conn.wait_for(STARTED, START_TIMEOUT_S)
        self.frames = FrameClock(fps, started.t_host_ns, written.seq_base(fps, started.t_host_ns), segment)
        self.output_file = Path(started.output_path) if started.output_path else None
        if self.marker is not None:
            self.marker.started_ns = started.t_host_ns
        self._wait_for_first_frame()
        log.info("%s: OBS %s recording at %s fps into %s (segment %d, seq from %d)", self.name,
                 version.get("obsVersion"), fps, folder, segment, self.frames.seq_base)
        info = {"model": f"OBS Studio {version.get('obsVersion')}", "obs_version": version.get("obsVersion"),
                "websocket_version": version.get("obsWebSocketVersion"), "fps": f"{fps.numerator}/{fps.denominator}",
                "resolution": f"{video['outputWidth']}x{video['outputHeight']}", "output_mode": mode,
                "file": self._relative(self.output_file), "segment": segment, "seq_base": self.frames.seq_base,
                "start_request_host_ns": request_ns, "start_ack_host_ns": ack_ns,
                "started_host_ns": started.t_host_ns, "saved_settings": str(self.store.path), **self._marker_info()}
        if restored:
            info["restored_stale_settings"] = restored
        return info

    def _save_operator_settings(self, target: RecordTarget, values: dict[tuple[str, str], str], folder: Path) -> None:
        """Save what OBS has now before changing it, unless this process saved it already (a reconnect:
        OBS may hold midas's own values by now, which must never become "the operator's")."""
        own = self.store.load()
        if own is not None:  # recover_stale left only this process's own copy
            self.saved = own
            saved_keys = {(category, name) for category, name, _ in own.profile}
            missing = [key for key in values if key not in saved_keys]  # never changed by midas: still the operator's
            own.profile += target.current(missing)
            if self.marker is not None and not own.scene_items:
                own.scene_items.append(self.marker.saved_state())
            if missing or self.marker is not None:
                self.store.replace(own)
            return
        saved = SavedSettings.for_this_process(self.store.address, folder, self.params["password_env"],
                                               self.params["password_file"])
        saved.profile = target.current(list(values))
        if self.marker is not None:
            saved.scene_items.append(self.marker.saved_state())
        if not self.store.save_new(saved):
            raise DeviceError(f"{self.name}: another process saved OBS's settings to {self.store.path} just now: "
                              f"is a second midas using OBS at {self.store.address}?")
        self.saved = saved

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

    def _wait_for_first_frame(self) -> None:
        """Return once OBS has muxed a frame: an encoder still starting up must not look like a stall."""
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            status = self.connection.request("GetRecordStatus")
            if not status.get("outputActive") or self.frames.frames_in(int(status.get("outputDuration", 0))) > 0:
                return  # a recording that stopped already is reported by the first read
            time.sleep(self.params["poll"] / 2)
        raise DeviceError(f"{self.name}: OBS started recording but wrote no frame within {START_TIMEOUT_S:.0f} s: "
                          f"see OBS's log (encoder problem?)")

    def _marker_info(self) -> dict[str, Any]:
        if self.marker is None:
            return {}
        return {"marker": {"scene": self.marker.scene, "source": self.marker.plan.source,
                           "scene_item_id": self.marker.item_id, "stream": f"{self.name}_marker"}}

    def _stream_file(self) -> Path:
        return self.session_dir / self.streams[0].file

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
        rows = self.frames.rows(self._next_frame, available)
        self._next_frame = max(self._next_frame, available)
        return rows

    def _obs_counters(self) -> dict[str, int]:
        stats = self.connection.request("GetStats")
        return {"output_skipped_frames": int(stats.get("outputSkippedFrames", 0)),
                "render_lagged_frames": int(stats.get("renderSkippedFrames", 0))}

    # -- stop -----------------------------------------------------------------------------------
    def finish(self) -> dict[str, list[tuple]]:
        """Stop OBS's recording, check every segment's file, and return the rows of the last file's last
        frames."""
        if self.frames is None or self.connection is None:
            return {}
        frames, rows_live = self.frames, self._next_frame
        counters = {k: v - self._counters_at_start.get(k, 0) for k, v in self._obs_counters().items()}
        stop_request_ns = self.clock.now_ns()
        path = self.connection.request("StopRecord").get("outputPath")
        stopped = self.connection.wait_for(STOPPED, STOP_TIMEOUT_S)
        self.frames = None  # stopped: close() has no recording of its own left to stop
        self.output_file = Path(stopped.output_path or path or self.output_file)
        segments, last_times = self._check_segments(frames, rows_live, counters)
        recording = {"status": "mismatch" if any(s["status"] != "ok" for s in segments) else "ok",
                     "segments": segments, "stop_request_host_ns": stop_request_ns,
                     "stopped_host_ns": stopped.t_host_ns}
        for key in ("frames_in_file", "rows_live", "rows_at_stop", "rows_without_frame", "frames_without_row"):
            recording[key] = sum(s[key] for s in segments)
        recording["problems"] = [f"segment {s['segment']}: {p}" for s in segments for p in s["problems"]]
        recording["warnings"] = [f"segment {s['segment']}: {w}" for s in segments for w in s["warnings"]]
        self.final_info = {"recording": recording}
        self._next_frame = max(rows_live, last_times)
        return {self.name: frames.rows(rows_live, last_times)}

    def _check_segments(self, frames: FrameClock, rows_live: int,
                        counters: dict[str, int]) -> tuple[list[dict[str, Any]], int]:
        """Each segment file of this session against the rows written for it; the final segment's
        frame count (its rows up to there are added at stop)."""
        folder = self.session_dir / "video"
        files = segment_files(folder, self.name)
        files[frames.segment] = self.output_file
        written = WrittenRows.read(self._stream_file(), frames.fps)
        entries, final_frames = [], rows_live
        for segment in sorted(set(files) | set(written.segments)):
            final = segment == frames.segment
            rows = written.segments.get(segment)
            rows_live_k = rows_live if final else (rows.rows if rows else 0)
            seq_base = frames.seq_base if final else (rows.seq_base() if rows else None)
            check = self._check_file(files.get(segment), frames.fps, rows_live_k, counters if final else None,
                                     final, seq_base)
            if final:
                final_frames = max(rows_live, check.frames_in_file)
            for text in check.problems + check.warnings:
                log.warning("%s: segment %d (%s): %s", self.name, segment, self._relative(files.get(segment)), text)
            started = frames.started_ns if final else (rows.started_ns(frames.fps) if rows else None)
            entries.append({"segment": segment, "file": self._relative(files.get(segment)), "seq_base": seq_base,
                            "started_host_ns": started, **check.to_manifest()})
        return entries, final_frames

    @staticmethod
    def _check_file(path: Path | None, fps: Fraction, rows_live: int, counters: dict[str, int] | None, final: bool,
                    seq_base: int | None) -> RecordingCheck:
        if path is None or not path.is_file():
            return unreadable_recording(rows_live, "no video file was found for this segment")
        try:
            times = probe_frame_times(path) if path.stat().st_size else np.zeros(0)  # killed before writing
        except DeviceError as exc:
            return unreadable_recording(rows_live, f"the file cannot be read ({exc})")
        return check_recording(times, fps, rows_live, counters, final, seq_base)

    def close(self) -> None:
        """Stop a recording this device started and did not finish (the device was lost), then put the
        operator's settings back from the saved copy and delete it; if OBS cannot be reached the copy is
        kept, for the next open (a reconnect), `midas record` or `midas doctor`."""
        if self.connection is None:
            return
        if self.frames is not None:
            self._stop_own_recording()
        if self.saved is not None:
            try:
                for warning in restore_settings(self.connection, self.saved):
                    log.warning("%s: %s", self.name, warning)
                self.store.delete()
            except DeviceError as exc:
                log.warning("%s: could not restore OBS's settings (%s); they stay saved in %s, and the next "
                            "`midas record` with this OBS or `midas doctor` puts them back", self.name, exc,
                            self.store.path)
        self.saved = self.marker = self.frames = None
        self.connection.close()
        self.connection = None

    def _stop_own_recording(self) -> None:
        try:
            stop_orphan_recording(self.connection, str((self.session_dir / "video").resolve()))
        except DeviceError as exc:  # OBS gone: nothing is recording any more
            log.info("%s: could not stop OBS's recording on close: %s", self.name, exc)

    def _relative(self, path: Path | None) -> str | None:
        if path is None:
            return None
        return os.path.relpath(path, self.session_dir.resolve())


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
