"""OBS backend without OBS: frame-clock arithmetic, the stop-time check, passwords, URLs, marker schedule,
and `midas record` failing fast (exit 3) when OBS cannot be reached."""

from __future__ import annotations

import time
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from helpers.cli import midas
from midas_cli.clock import HostClock
from midas_cli.devices.obs.connection import ObsConnection, resolve_password
from midas_cli.devices.obs.frames import FrameClock, WrittenRows, check_recording, segment_files
from midas_cli.devices.obs.marker import MarkerPlan, SyncMarker
from midas_cli.devices.obs.profile import recover_stale
from midas_cli.devices.obs.saved import SavedSettings, SettingsStore
from midas_cli.processes import process_start
from midas_cli.devices.registry import describe_device
from midas_cli.devices.rigconfig import parse_rig
from midas_cli.errors import ConfigError, DeviceError
from helpers.net import free_port


@pytest.fixture(autouse=True)
def _own_state_dir(tmp_path, monkeypatch) -> None:
    """Saved OBS settings go under the test's folder, never the user's ~/.local/state."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "xdg-state"))


@pytest.mark.parametrize("fps", [Fraction(30), Fraction(30000, 1001), Fraction(60000, 1001), Fraction(25)])
def test_frame_count_is_recovered_from_obs_truncated_duration(fps: Fraction) -> None:
    clock = FrameClock(fps, 0)
    frame_ns = int(10**9 / fps)  # OBS: video_output_get_frame_time, integer ns
    for frames in range(0, 20000, 7):
        duration_ms = frames * frame_ns // 1_000_000  # GetRecordStatus outputDuration
        assert clock.frames_in(duration_ms) == frames


def test_frame_rows_follow_started_plus_index_over_fps() -> None:
    clock = FrameClock(Fraction(30000, 1001), started_ns=1_000_000_000_000, seq_base=10, segment=2)
    rows = clock.rows(0, 3)
    assert [r[0] for r in rows] == [10, 11, 12] and {r[3] for r in rows} == {2}
    assert rows[1][1] - rows[0][1] == 33_366_667 and rows[2][2] == pytest.approx(2 * 1001 / 30000)
    late = clock.rows(30000, 30001)[0]  # exact over long recordings: no float drift
    assert late[1] == 1_000_000_000_000 + 1001 * 10**9


def _video_csv(path, rows) -> None:
    path.write_text("seq,t_host_ns,t_device_s,segment\n" + "".join(f"{s},{t},{d:.6f},{k}\n" for s, t, d, k in rows))


def test_a_new_segment_continues_seq_on_the_first_segments_frame_grid(tmp_path) -> None:
    fps = Fraction(30)
    t0 = 1_795_547_220_591_118_411  # Unix-epoch ns: more digits than a float holds
    first = FrameClock(fps, started_ns=t0)
    _video_csv(tmp_path / "video.csv", first.rows(0, 158))  # killed at ~5.3 s
    written = WrittenRows.read(tmp_path / "video.csv", fps)
    assert written.last_seq == 157 and written.origin_ns == t0 and written.next_segment({}) == 1
    restarted_ns = t0 + 13_010_000_000  # 13.01 s after the first STARTED: frame 390.3 of the grid
    assert written.seq_base(fps, restarted_ns) == 390
    assert written.seq_base(fps, t0 + 1_000_000_000) == 158  # never back (a clock step)
    second = FrameClock(fps, restarted_ns, written.seq_base(fps, restarted_ns), segment=1)
    _video_csv(tmp_path / "video.csv", first.rows(0, 158) + second.rows(0, 30))
    again = WrittenRows.read(tmp_path / "video.csv", fps)
    assert again.segments[1].seq_base() == 390 and again.segments[1].started_ns(fps) == restarted_ns
    assert again.segments[0].rows == 158 and again.segments[0].started_ns(fps) == t0
    assert again.segments[0].last_seq == 157 and again.next_segment({3: tmp_path / "x.mkv"}) == 4
    assert WrittenRows.read(tmp_path / "absent.csv", fps).seq_base(fps, restarted_ns) == 0


def test_segment_files_are_found_by_device_and_index(tmp_path) -> None:
    for name in ("video_s0_2026-01-01_10-00-00.mkv", "video_s1_2026-01-01_10-00-09.mkv",
                 "video_side_s0_2026-01-01_10-00-00.mkv", "video_s2_notes.txt"):
        (tmp_path / name).touch()
    assert {k: p.name for k, p in segment_files(tmp_path, "video").items()} == {
        0: "video_s0_2026-01-01_10-00-00.mkv", 1: "video_s1_2026-01-01_10-00-09.mkv"}


def test_check_of_a_killed_segment_reports_rows_without_frames() -> None:
    times = np.arange(104) / 30
    check = check_recording(times, Fraction(30), rows_live=158, obs_counters=None, final=False, seq_base=0)
    assert check.to_manifest()["status"] == "mismatch" and check.rows_without_frame == 54
    assert check.rows_at_stop == 0 and "seq 104..157" in check.problems[0] and "killed" in check.problems[0]
    tail = check_recording(times, Fraction(30), rows_live=100, obs_counters=None, final=False, seq_base=0)
    assert tail.to_manifest()["status"] == "ok" and tail.frames_without_row == 4 and tail.rows_at_stop == 0


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
    assert "marked failed" in result.stderr and "Traceback" not in result.stderr


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
    assert connection.sent == [] and marker.saved_state() == {"scene": "Scene", "item_id": 7, "enabled": True}
    marker.hide()
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


class FakeObs:
    """Profile parameters, a record status and scene items, as obs-websocket answers them."""

    def __init__(self, profile: dict, recording_into: str | None = None) -> None:
        self.profile, self.recording_into, self.items, self.requests = dict(profile), recording_into, {}, []

    def request(self, name: str, data: dict | None = None) -> dict:
        self.requests.append(name)
        if name == "GetProfileParameter":
            return {"parameterValue": self.profile.get((data["parameterCategory"], data["parameterName"]))}
        if name == "SetProfileParameter":
            key = (data["parameterCategory"], data["parameterName"])
            if data["parameterValue"] is None:
                self.profile.pop(key, None)
            else:
                self.profile[key] = data["parameterValue"]
        if name == "GetRecordStatus":
            return {"outputActive": self.recording_into is not None}
        if name == "GetRecordDirectory":
            return {"recordDirectory": self.recording_into or self.profile[("SimpleOutput", "FilePath")]}
        if name == "StopRecord":
            self.recording_into = None
        if name == "SetSceneItemEnabled":
            self.items[data["sceneItemId"]] = data["sceneItemEnabled"]
        return {}

    def wait_for(self, state: str, timeout_s: float):
        return None


def _dead_pid() -> int:
    import subprocess
    import sys

    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_saved_copy_is_written_once_and_knows_its_owner(tmp_path) -> None:
    store = SettingsStore("127.0.0.1", 4455)
    assert store.path == tmp_path / "xdg-state" / "midas" / "obs-settings-127.0.0.1-4455.json"
    first = SavedSettings.for_this_process(store.address, tmp_path / "s1" / "video", "")
    first.profile = [["SimpleOutput", "FilePath", "/home/op/Videos"], ["Output", "FilenameFormatting", None]]
    assert store.save_new(first) and store.load() == first and store.load().owner() == "self"
    second = SavedSettings.for_this_process(store.address, tmp_path / "s2" / "video", "")
    second.profile = [["SimpleOutput", "FilePath", str(tmp_path / "s1" / "video")]]
    assert not store.save_new(second)  # a reconnect never overwrites the operator's values with midas's
    assert store.load().profile[0][2] == "/home/op/Videos" and not list(store.path.parent.glob(".*tmp"))
    other = SavedSettings(**{**first.__dict__, "owner_pid": 1, "owner_start": ""})
    assert other.owner() == "alive"  # pid 1 runs (the PID alone decides without a start time)
    assert SavedSettings(**{**first.__dict__, "owner_pid": _dead_pid()}).owner() == "stale"
    assert SavedSettings(**{**first.__dict__, "owner_start": "1"}).owner() == "stale"  # PID reused


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="zombies are told apart through /proc")
def test_an_owner_killed_but_not_yet_reaped_is_gone(tmp_path) -> None:
    """A SIGKILLed midas whose parent never reaps it (a container whose PID 1 reaps nobody) stays a
    zombie with its PID and start time: its copy is stale all the same, not 'in use by another midas'."""
    import subprocess
    import sys

    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        saved = SavedSettings.for_this_process("127.0.0.1:4455", tmp_path / "s" / "video", "")
        owned = SavedSettings(**{**saved.__dict__, "owner_pid": child.pid, "owner_start": process_start(child.pid)})
        assert owned.owner_start and owned.owner() == "alive"
        child.kill()
        deadline = time.monotonic() + 60
        while Path(f"/proc/{child.pid}/stat").read_text().split(")")[-1].split()[0] != "Z":  # killed, unreaped
            assert time.monotonic() < deadline, "the child never became a zombie"
            time.sleep(0.01)
        assert process_start(child.pid) is None and owned.owner() == "stale"
    finally:
        child.kill()
        child.wait()


def test_a_stale_copy_is_restored_and_the_orphan_recording_stopped(tmp_path) -> None:
    folder = str(tmp_path / "session" / "video")
    store = SettingsStore("127.0.0.1", 4455, tmp_path)
    saved = SavedSettings.for_this_process(store.address, tmp_path / "session" / "video", "")
    saved.profile = [["SimpleOutput", "FilePath", "/home/op/Videos"], ["Output", "FilenameFormatting", None]]
    saved.scene_items = [{"scene": "Scene", "item_id": 2, "enabled": True}]
    obs = FakeObs({("SimpleOutput", "FilePath"): folder, ("Output", "FilenameFormatting"): "video_s0_%CCYY"},
                  recording_into=folder)
    store.save_new(saved)
    assert recover_stale(obs, store) is None and store.path.exists()  # this process's own copy: kept
    store.replace(SavedSettings(**{**saved.__dict__, "owner_pid": _dead_pid()}))
    text = recover_stale(obs, store)
    assert "restored the recording settings" in text and "SimpleOutput.FilePath=/home/op/Videos" in text
    assert f"midas session repair {tmp_path / 'session'}" in text and not store.path.exists()
    assert obs.profile == {("SimpleOutput", "FilePath"): "/home/op/Videos"} and obs.recording_into is None
    assert obs.items == {2: True}
    store.save_new(SavedSettings(**{**saved.__dict__, "owner_pid": 1, "owner_start": ""}))
    with pytest.raises(DeviceError, match="in use by another midas"):
        recover_stale(obs, store)
