"""`midas record` against a real OBS Studio (headless, see obs_fixture.py): the MKV, one timestamp row
per encoded frame, the stop-time check, the sync marker, and the password kept out of every output."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from helpers.cli import midas, record_until
from midas_cli.analysis.video_marker import marker_offsets_ms, marker_onsets, region_brightness
from helpers.obs_fixture import FPS, MARKER, MARKER_ROI, ObsServer, running_obs

pytestmark = pytest.mark.slow
PASSWORD = "obs-test-Pa55word-7d1f"


@pytest.fixture(scope="module")
def obs(tmp_path_factory) -> ObsServer:
    with running_obs(tmp_path_factory.mktemp("obs-home"), PASSWORD) as server:
        yield server


def _record(obs: ObsServer, out: Path, duration: float):
    return midas("record", "--device", f"video=obs://127.0.0.1:{obs.port}", "--duration", str(duration),
                 "--out", str(out), "--subject", "1", "--task", "obs", "--trial", "1", "--no-tui", timeout=240)


@pytest.fixture(scope="module")
def state_home(tmp_path_factory) -> Path:
    """XDG_STATE_HOME for every midas this module runs: saved OBS settings never reach the user's own."""
    return tmp_path_factory.mktemp("xdg-state")


@pytest.fixture(autouse=True)
def _own_state_dir(state_home: Path, monkeypatch) -> None:
    monkeypatch.setenv("XDG_STATE_HOME", str(state_home))


@pytest.fixture(scope="module")
def recorded(obs: ObsServer, state_home: Path, tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("sessions")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MIDAS_OBS_PASSWORD", PASSWORD)
        patch.setenv("XDG_STATE_HOME", str(state_home))
        # stopped (Ctrl-C) once four toggles of the marker are on disk (shown, hidden, shown, hidden): a busy
        # host may start OBS late, and a marker shown just before the stop may not reach an encoded frame
        args = ["--device", f"video=obs://127.0.0.1:{obs.port}?fps={FPS}&marker={MARKER}&marker_at=1&marker_every=2",
                "--subject", "1", "--task", "obs", "--trial", "1", "--no-tui"]
        result = record_until(out, args, rows={"video": 1, "video_marker": 4}, timeout=240)
    assert result.returncode == 0, result.stderr
    return Path(result.stdout.strip().splitlines()[-1]), result


def _ffprobe_frames(path: Path) -> dict:
    result = subprocess.run(["ffprobe", "-v", "error", "-select_streams", "v:0", "-count_frames", "-show_entries",
                             "stream=codec_name,nb_read_frames,r_frame_rate", "-of", "json", str(path)],
                            capture_output=True, text=True, check=True)
    return json.loads(result.stdout)["streams"][0]


def test_the_mkv_plays_and_has_one_timestamp_row_per_encoded_frame(recorded) -> None:
    session, _ = recorded
    videos = sorted((session / "video").glob("*.mkv"))
    assert len(videos) == 1
    probe = _ffprobe_frames(videos[0])
    frames = int(probe["nb_read_frames"])
    assert probe["codec_name"] == "h264" and probe["r_frame_rate"] == f"{FPS}/1"
    manifest = json.loads((session / "manifest.json").read_text())
    recorded_s = (manifest["stop"]["host_ns"] - manifest["devices"]["video"]["info"]["started_host_ns"]) / 1e9
    assert recorded_s > 1 and frames >= (recorded_s - 0.5) * FPS  # from OBS's STARTED to midas's stop
    decode = subprocess.run(["ffmpeg", "-v", "error", "-i", str(videos[0]), "-f", "null", "-"],
                            capture_output=True, text=True)
    assert decode.returncode == 0 and decode.stderr == ""
    rows = pd.read_csv(session / "streams" / "video.csv")
    assert len(rows) == frames
    assert rows["seq"].tolist() == list(range(frames)) and set(rows["segment"]) == {0}
    np.testing.assert_allclose(rows["t_device_s"], rows["seq"] / FPS, atol=1e-6)
    steps = np.diff(rows["t_host_ns"].to_numpy())
    assert steps.min() >= 33_333_333 and steps.max() <= 33_333_334


def test_manifest_reports_the_start_event_and_the_stop_check(recorded) -> None:
    session, _ = recorded
    manifest = json.loads((session / "manifest.json").read_text())
    info = manifest["devices"]["video"]["info"]
    rows = pd.read_csv(session / "streams" / "video.csv")
    assert info["obs_version"].startswith(("29.", "30.", "31.")) and info["fps"] == f"{FPS}/1"
    assert info["start_request_host_ns"] <= info["started_host_ns"] == rows["t_host_ns"].iloc[0]
    check = info["recording"]
    assert check["status"] == "ok", check
    assert check["frames_in_file"] == len(rows) == check["rows_live"] + check["rows_at_stop"]
    assert check["rows_without_frame"] == check["frames_without_row"] == 0
    [segment] = check["segments"]
    assert segment["segment"] == 0 and segment["seq_base"] == 0 and segment["frames_in_file"] == len(rows)
    assert segment["started_host_ns"] == info["started_host_ns"] and segment["status"] == "ok"
    assert segment["file"] == info["file"] and segment["file"].startswith("video/video_s0_")
    assert (session / segment["file"]).is_file()
    assert check["stopped_host_ns"] > check["stop_request_host_ns"] > info["started_host_ns"]
    assert set(segment["obs_counters"]) == {"output_skipped_frames", "render_lagged_frames"}
    assert info["password_from"] == "$MIDAS_OBS_PASSWORD"
    assert midas("session", "verify", str(session)).returncode == 0


def test_sync_marker_is_found_in_the_pixels_near_its_host_time(recorded) -> None:
    session, _ = recorded
    toggles = pd.read_csv(session / "streams" / "video_marker.csv")
    enabled = toggles["enabled"].tolist()  # shown, hidden, shown, hidden, ... (recorded until four were on disk)
    assert len(enabled) >= 4 and enabled == [1 - i % 2 for i in range(len(enabled))]
    assert (toggles["t_ack_ns"] >= toggles["t_host_ns"]).all()
    video = next((session / "video").glob("*.mkv"))
    onsets = marker_onsets(region_brightness(video, MARKER_ROI))
    frames = pd.read_csv(session / "streams" / "video.csv")["t_host_ns"].to_numpy()
    shown = toggles.loc[toggles["enabled"] == 1, "t_host_ns"].to_numpy()
    # every showing half a second or more before the last encoded frame is in the pixels (a busy OBS renders
    # late: one shown just before the stop may never reach the file), and the video shows no marker not asked for
    settled = int(np.sum(shown < frames[-1] - 500_000_000))
    offsets = marker_offsets_ms(frames, onsets, shown)
    assert settled >= 2 and settled <= len(onsets) <= len(shown), (settled, onsets, shown)
    assert not np.isnan(offsets[:settled]).any(), offsets
    assert np.all(np.abs(offsets[~np.isnan(offsets)]) < 500), offsets  # next to its own toggle, not a neighbour's


def test_the_password_never_reaches_outputs_and_obs_settings_are_restored(recorded, obs: ObsServer,
                                                                          state_home: Path) -> None:
    session, result = recorded
    for path in [session / "manifest.json", session / "logs" / "midas.log", *session.glob("streams/*.csv")]:
        assert PASSWORD not in path.read_text(), path
    assert not list(state_home.rglob("*.json"))  # the saved copy is deleted once OBS has its values back
    assert PASSWORD not in result.stdout + result.stderr
    import obsws_python

    client = obsws_python.ReqClient(host="127.0.0.1", port=obs.port, password=PASSWORD, timeout=5)
    try:
        def value(category: str, name: str):
            return client.send("GetProfileParameter", {"parameterCategory": category, "parameterName": name},
                               raw=True)["parameterValue"]

        assert value("SimpleOutput", "FilePath") == str(obs.default_folder)
        assert value("SimpleOutput", "RecFormat") == "flv"
        enabled = client.send("GetSceneItemEnabled", {"sceneName": "Scene", "sceneItemId": 2}, raw=True)
        assert enabled["sceneItemEnabled"] is False
    finally:
        client.disconnect()


@pytest.mark.parametrize("password, expected", [("not-the-password", "refused the connection"),
                                                (None, "requires a password")])
def test_bad_or_missing_password_fails_before_recording(obs: ObsServer, tmp_path: Path, monkeypatch,
                                                        password, expected) -> None:
    if password is None:
        monkeypatch.delenv("MIDAS_OBS_PASSWORD", raising=False)
    else:
        monkeypatch.setenv("MIDAS_OBS_PASSWORD", password)
    result = _record(obs, tmp_path, duration=30)
    assert result.returncode == 3, result.stderr
    assert expected in result.stderr and "Traceback" not in result.stderr
    assert password is None or password not in result.stderr + result.stdout
    session = next(tmp_path.iterdir())
    assert not list((session / "video").iterdir())


def test_a_mixed_session_with_obs_emulators_and_lsl_verifies(obs: ObsServer, tmp_path: Path) -> None:
    """Issue 4's mixed rig: simulated EmHT + the FPS board emulator + a real OBS + the Raven emulator
    + an LSL stream, one `midas record`, one session that `midas session verify` accepts."""
    from midas_cli.devices.fps.emulator import FpsEmulator, FpsEmulatorConfig
    from midas_cli.devices.raven.emulator import RavenEmulator, RavenEmulatorConfig
    from midas_cli.session.reader import Session
    from helpers.lsl_fixture import CounterOutlet, loopback_lsl_config
    from helpers.net import free_udp_port

    pytest.importorskip("pylsl", reason="pylsl is not installed")
    loopback_lsl_config(tmp_path)
    port = free_udp_port()
    with pytest.MonkeyPatch.context() as patch, FpsEmulator(FpsEmulatorConfig(channels=9)) as board, \
            RavenEmulator(RavenEmulatorConfig("127.0.0.1", port, rate_hz=200)), \
            CounterOutlet("midas-test-obs-mixed", rate=50.0):
        patch.setenv("MIDAS_OBS_PASSWORD", PASSWORD)
        # stopped (Ctrl-C) once every device has rows on disk: how fast each opens depends on the host's load
        args = ["--device", "emht=sim://emht", "--device", f"fps=fps://{board.path}?rate=200",
                "--device", f"video=obs://127.0.0.1:{obs.port}?fps={FPS}",
                "--device", f"raven=raven://127.0.0.1:{port}?rate=200",
                "--device", "hr=lsl://?name=midas-test-obs-mixed", "--subject", "1",
                "--task", "mixed", "--trial", "1", "--no-tui"]
        result = record_until(tmp_path / "sessions", args, rows=dict.fromkeys(("emht", "fps", "video", "raven", "hr"), 5),
                              timeout=240)
    assert result.returncode == 0, result.stderr
    path = Path(result.stdout.strip().splitlines()[-1])
    verify = midas("session", "verify", str(path))
    assert verify.returncode == 0, verify.stdout + verify.stderr
    session = Session.open(path)
    assert {"emht", "fps", "video", "raven", "hr"} <= set(session.stream_names)
    assert all(session.manifest["streams"][name]["samples"] > 0 for name in session.stream_names
               if name != "events")  # the operator's markers: none here
    # one segment, or more if a busy host stalled OBS past the stall timeout (a reconnect, explained)
    segments = list((path / "video").glob("*.mkv"))
    assert len(segments) == 1 + session.manifest["devices"]["video"]["reconnects"]
