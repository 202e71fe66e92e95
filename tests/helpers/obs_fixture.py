"""A real OBS Studio for tests: headless under Xvfb, websocket on a free loopback port, password set.

Everything lives in a temporary HOME/XDG_CONFIG_HOME: ``global.ini`` enables obs-websocket in its
``[OBSWebSocket]`` section (the keys OBS 29 / obs-websocket 5.1 read: FirstLoad, ServerEnabled,
ServerPort, AlertsEnabled, AuthRequired, ServerPassword), a 320x240 @ 30 fps profile encoding with
x264, and a scene of colour sources (they render with Mesa's software OpenGL, no GPU): a black
background and a white 80x60 ``Marker`` in the top-left corner, hidden. Skips with the reason when
OBS, Xvfb or ffprobe are not installed (CI installs: obs-studio xvfb xauth ffmpeg). ``obs_process``
gives an ``ObsProcess`` that a test can kill (SIGKILL) and start again on the same port and configuration.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import pytest

from helpers.net import free_port

START_TIMEOUT_S = 90.0
FPS = 30
MARKER = "Marker"
MARKER_ROI = (0, 0, 80, 60)  # x, y, width, height in the 320x240 frame


@dataclass(frozen=True)
class ObsServer:
    port: int
    password: str
    config_home: Path
    default_folder: Path
    log: Path


def missing_tools() -> list[str]:
    return [tool for tool in ("obs", "xvfb-run", "Xvfb", "ffprobe") if shutil.which(tool) is None]



def _ini(sections: dict[str, dict[str, object]]) -> str:
    return "".join(f"[{name}]\n" + "".join(f"{k}={v}\n" for k, v in keys.items()) + "\n"
                   for name, keys in sections.items())


def _color_source(name: str, uuid: str, argb: int, width: int, height: int) -> dict:
    return {"id": "color_source", "versioned_id": "color_source_v3", "name": name, "uuid": uuid,
            "settings": {"color": argb, "width": width, "height": height}}


def _scene_item(item_id: int, source: dict, visible: bool) -> dict:
    return {"name": source["name"], "source_uuid": source["uuid"], "id": item_id, "visible": visible,
            "locked": False, "pos": {"x": 0, "y": 0}, "scale": {"x": 1, "y": 1}, "align": 5,
            "bounds_type": 0, "bounds": {"x": 0, "y": 0}, "rot": 0}


def write_config(home: Path, port: int, password: str) -> ObsServer:
    """OBS's whole configuration under ``home`` (used as HOME and XDG_CONFIG_HOME/..)."""
    obs = home / ".config" / "obs-studio"
    (obs / "basic" / "profiles" / "midas").mkdir(parents=True)
    (obs / "basic" / "scenes").mkdir(parents=True)
    default_folder = home / "obs-default-recordings"
    default_folder.mkdir()
    (obs / "global.ini").write_text(_ini({
        "General": {"FirstRun": "true", "LastVersion": 486539266, "EnableAutoUpdates": "false"},
        "Basic": {"Profile": "midas", "ProfileDir": "midas", "SceneCollection": "midas",
                  "SceneCollectionFile": "midas", "ConfigOnNewProfile": "false"},
        "OBSWebSocket": {"FirstLoad": "false", "ServerEnabled": "true", "ServerPort": port,
                         "AlertsEnabled": "false", "AuthRequired": "true", "ServerPassword": password},
    }))
    (obs / "basic" / "profiles" / "midas" / "basic.ini").write_text(_ini({
        "General": {"Name": "midas"},
        "Video": {"BaseCX": 320, "BaseCY": 240, "OutputCX": 320, "OutputCY": 240, "FPSType": 0, "FPSCommon": FPS},
        "Output": {"Mode": "Simple"},
        "SimpleOutput": {"FilePath": default_folder, "RecFormat": "flv", "RecQuality": "Stream",
                         "StreamEncoder": "x264", "VBitrate": 300, "Preset": "ultrafast"},
        "Audio": {"SampleRate": 48000, "ChannelSetup": "Mono"},
    }))
    background = _color_source("Background", "22222222-2222-4222-8222-222222222222", 0xFF000000, 320, 240)
    marker = _color_source(MARKER, "33333333-3333-4333-8333-333333333333", 0xFFFFFFFF, *MARKER_ROI[2:])
    scene = {"id": "scene", "versioned_id": "scene", "name": "Scene", "uuid": "11111111-1111-4111-8111-111111111111",
             "settings": {"id_counter": 2, "items": [_scene_item(1, background, True), _scene_item(2, marker, False)]}}
    collection = {"name": "midas", "current_scene": "Scene", "current_program_scene": "Scene",
                  "scene_order": [{"name": "Scene"}], "sources": [scene, background, marker]}
    (obs / "basic" / "scenes" / "midas.json").write_text(json.dumps(collection))
    return ObsServer(port, password, home / ".config", default_folder, home / "obs.log")


def _wait_for_port(port: int, process: subprocess.Popen, log: Path) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if process.poll() is not None:
            pytest.skip(f"OBS exited during start-up ({process.returncode}): {log.read_text()[-1500:]}")
        with socket.socket() as probe:
            if probe.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.25)
    pytest.skip(f"OBS's websocket did not open port {port} within {START_TIMEOUT_S:.0f} s: {log.read_text()[-1500:]}")


class ObsProcess:
    """One OBS under xvfb-run that a test can kill (SIGKILL, like a crash) and start again on the same
    port with the same configuration (HOME, profile, scene collection, websocket password)."""

    def __init__(self, home: Path, password: str) -> None:
        missing = missing_tools()
        if missing:
            pytest.skip(f"OBS test needs {', '.join(missing)} (apt-get install obs-studio xvfb xauth ffmpeg)")
        self.home = home
        self.server = write_config(home, free_port(), password)
        self.env = {**os.environ, "HOME": str(home), "XDG_CONFIG_HOME": str(self.server.config_home),
                    "LIBGL_ALWAYS_SOFTWARE": "1", "QT_QPA_PLATFORM": "xcb"}
        self.process: subprocess.Popen | None = None
        self.starts = 0

    def start(self) -> None:
        """Launch OBS (own process group, ended by its id afterwards) and wait for its websocket port."""
        self.starts += 1
        log_path = self.server.log if self.starts == 1 else self.server.log.with_suffix(f".{self.starts}.log")
        with open(log_path, "wb") as log:
            self.process = subprocess.Popen(["xvfb-run", "-a", "-s", "-screen 0 640x480x24", "obs",
                                             "--minimize-to-tray", "--multi", "--disable-missing-files-check"],
                                            cwd=self.home, env=self.env, stdout=log, stderr=subprocess.STDOUT,
                                            start_new_session=True)
        _wait_for_port(self.server.port, self.process, log_path)

    def pids(self, *names: str) -> list[int]:
        """Processes named ``names`` in this instance's process group (``obs``: xvfb-run's child;
        ``obs-ffmpeg-mux``: the muxer OBS starts for each recording, which writes the file)."""
        assert self.process is not None and self.process.poll() is None, "OBS is not running"
        found = []
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                text = stat.read_text()
            except OSError:  # the process ended while listing
                continue
            comm = text[text.index("(") + 1 : text.rindex(")")]
            fields = text[text.rindex(")") + 2 :].split()
            if comm in names and int(fields[2]) == self.process.pid:  # fields[2]: process group id
                found.append(int(stat.parent.name))
        return found

    def kill_obs(self, with_muxer: bool = True) -> None:
        """SIGKILL OBS and, ``with_muxer``, the muxer writing its recording (as ``pkill -9 obs`` does: the
        pattern matches obs-ffmpeg-mux too): nothing is flushed or saved, so the file lacks the frames the
        muxer still buffered (an MKV cluster's worth, or all of them in the first seconds). Killed alone,
        OBS leaves the muxer to finish the file. xvfb-run then ends its X server and exits. Waits until
        the websocket port is closed."""
        pids = self.pids("obs", *(("obs-ffmpeg-mux",) if with_muxer else ()))
        assert pids, f"no obs process in process group {self.process.pid}"
        for pid in pids:
            os.kill(pid, signal.SIGKILL)
        self.process.wait(timeout=30)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            with socket.socket() as probe:
                if probe.connect_ex(("127.0.0.1", self.server.port)) != 0:
                    return
            time.sleep(0.1)
        raise AssertionError(f"port {self.server.port} still open 30 s after OBS was killed")

    def stop(self) -> None:
        if self.process is not None:
            _stop(self.process)


@contextmanager
def obs_process(home: Path, password: str) -> Iterator[ObsProcess]:
    """A started ``ObsProcess``, stopped afterwards whatever state the test left it in."""
    instance = ObsProcess(home, password)
    try:
        instance.start()
        yield instance
    finally:
        instance.stop()


@contextmanager
def running_obs(home: Path, password: str) -> Iterator[ObsServer]:
    """Start OBS under xvfb-run (own process group, ended by its id afterwards) and wait for its port."""
    with obs_process(home, password) as instance:
        yield instance.server


def _stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait(timeout=5)
