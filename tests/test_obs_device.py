"""OBS backend without OBS: frame-clock arithmetic, the stop-time check, passwords, URLs, marker schedule,
and `midas record` failing fast (exit 3) when OBS cannot be reached."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from conftest import midas
from midas_cli.clock import HostClock
from midas_cli.devices.obs.connection import ObsConnection, resolve_password
from midas_cli.devices.obs.frames import FrameClock, check_recording
from midas_cli.devices.obs.marker import MarkerPlan, SyncMarker
from midas_cli.devices.registry import describe_device
from midas_cli.errors import ConfigError, DeviceError
from midas_cli.rig import parse_rig
from obs_fixture import free_port


@pytest.mark.parametrize("fps", [Fraction(30), Fraction(30000, 1001), Fraction(60000, 1001), Fraction(25)])
def test_frame_count_is_recovered_from_obs_truncated_duration(fps: Fraction) -> None:
    clock = FrameClock(fps, 0)
    frame_ns = int(10**9 / fps)  # OBS: video_output_get_frame_time, integer ns
    for frames in range(0, 20000, 7):
        duration_ms = frames * frame_ns // 1_000_000  # GetRecordStatus outputDuration
        assert clock.frames_in(duration_ms) == frames


def test_frame_rows_follow_started_plus_index_over_fps() -> None:
    clock = FrameClock(Fraction(30000, 1001), started_ns=1_000_000_000_000)
    rows = clock.rows(0, 3, seq_base=10)
    assert [r[0] for r in rows] == [10, 11, 12]
    assert rows[1][1] - rows[0][1] == 33_366_667 and rows[2][2] == pytest.approx(2 * 1001 / 30000)
    late = clock.rows(30000, 30001)[0]  # exact over long recordings: no float drift
    assert late[1] == 1_000_000_000_000 + 1001 * 10**9


def test_check_of_a_clean_file_is_ok() -> None:
    times = np.arange(150) / 30 + np.random.default_rng(0).uniform(-5e-4, 5e-4, 150)  # MKV: 1 ms time base
    check = check_recording(times, Fraction(30), rows_live=143, obs_counters={"output_skipped_frames": 0})
    manifest = check.to_manifest()
    assert manifest["status"] == "ok" and check.rows_at_stop == 7 and check.frames_in_file == 150


def test_check_finds_dropped_frames_extra_rows_and_counters() -> None:
    times = np.delete(np.arange(100) / 30, 40)  # frame 40 never encoded: the rest are a frame late
    check = check_recording(times, Fraction(30), rows_live=100, obs_counters={"output_skipped_frames": 1})
    assert check.to_manifest()["status"] == "mismatch"
    assert check.first_off_grid == 40 and check.frames_off_grid == 59
    assert any("1 row(s) were written live" in p for p in check.problems)
    assert check.warnings == ["OBS counted 1 output skipped frames during the recording"]


def test_password_comes_from_the_named_variable_or_the_default_one(monkeypatch) -> None:
    monkeypatch.delenv("MIDAS_OBS_PASSWORD", raising=False)
    assert resolve_password("") == ("", "none")
    monkeypatch.setenv("MIDAS_OBS_PASSWORD", "default-secret")
    assert resolve_password("") == ("default-secret", "$MIDAS_OBS_PASSWORD")
    monkeypatch.setenv("RIG_OBS_PW", "rig-secret")
    assert resolve_password("RIG_OBS_PW") == ("rig-secret", "$RIG_OBS_PW")
    with pytest.raises(ConfigError, match=r"\$UNSET_OBS_PW .* not set"):
        resolve_password("UNSET_OBS_PW")


@pytest.mark.parametrize("url", ["obs://user:hunter2@127.0.0.1:4455", "obs://127.0.0.1:4455?password=hunter2"])
def test_a_password_in_the_url_is_refused_without_echoing_it(url: str) -> None:
    with pytest.raises(ConfigError) as error:
        describe_device("video", url)
    assert "hunter2" not in str(error.value) and "environment variable" in str(error.value)


def test_rig_password_env_reaches_the_device_as_a_variable_name() -> None:
    rig = parse_rig({"rig": {"name": "r", "platform": "p"},
                     "devices": {"video": {"url": "obs://localhost:4455?fps=30", "password_env": "OBS_PW"}}}, "r.toml")
    url = rig.device_urls()["video"]
    assert url == "obs://localhost:4455?fps=30&password_env=OBS_PW"
    assert describe_device("video", url).settings()["password_env"] == "OBS_PW"


def test_unreachable_obs_is_a_clear_device_error() -> None:
    port = free_port()
    with pytest.raises(DeviceError, match=f"cannot reach OBS's websocket server at 127.0.0.1:{port}"):
        ObsConnection("127.0.0.1", port, "", 1.0, HostClock.anchored_now())


def test_record_fails_fast_with_exit_3_when_obs_is_unreachable(tmp_path) -> None:
    port = free_port()
    result = midas("record", "--device", f"video=obs://127.0.0.1:{port}", "--duration", "30", "--out", str(tmp_path),
                   "--subject", "1", "--task", "t", "--trial", "1", "--no-tui", timeout=60)
    assert result.returncode == 3, result.stderr
    assert f"cannot reach OBS's websocket server at 127.0.0.1:{port}" in result.stderr
    assert "kept as interrupted" in result.stderr and "Traceback" not in result.stderr


class FakeConnection:
    """Answers the marker's requests and remembers the enable states it was sent."""

    def __init__(self) -> None:
        self.sent: list[bool] = []

    def request(self, name: str, data: dict | None = None) -> dict:
        if name == "GetCurrentProgramScene":
            return {"currentProgramSceneName": "Scene"}
        if name == "GetSceneItemId":
            return {"sceneItemId": 7}
        if name == "GetSceneItemEnabled":
            return {"sceneItemEnabled": True}
        self.sent.append(data["sceneItemEnabled"])
        return {}


def test_marker_schedule_shows_and_hides_at_the_planned_host_times() -> None:
    connection = FakeConnection()
    marker = SyncMarker(MarkerPlan("Marker", at=1.0, on=0.5, every=2.0), connection, HostClock(0))
    assert connection.sent == [False] and marker.next_due_ns() is None  # hidden until the recording starts
    marker.started_ns = 0
    due = []
    for _ in range(4):
        due.append(marker.next_due_ns())
        marker.toggles += 1
    assert due == [1_000_000_000, 1_500_000_000, 3_000_000_000, 3_500_000_000]
    marker.restore()
    assert connection.sent[-1] is True  # the operator had it shown


def test_marker_plan_refuses_overlapping_showings() -> None:
    with pytest.raises(ConfigError, match="marker_every"):
        describe_device("video", "obs://127.0.0.1:4455?marker=M&marker_every=0.5&marker_on=0.5")
    assert MarkerPlan("M", at=1.0, on=0.5).spec("video").name == "video_marker"
