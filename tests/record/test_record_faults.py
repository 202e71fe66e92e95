"""Issue 13's fault matrix for `midas record`, driven through the CLI as a technician or a script would:
signals at any instant, kills of the whole process group, failed starts, scripts reading stdout, the
operator's screen and summary, and option values. The OBS cases live in test_record_faults_obs.py.

Nothing here assumes the machine's speed: waits are for files and lines to appear, and every
duration check allows for a busy 2-core machine."""

from __future__ import annotations

import json
import os
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rich.console import Console

from midas_cli.console import dashboard
from midas_cli.devices.fps.emulator import FpsEmulator, FpsEmulatorConfig
from midas_cli.record.status import DeviceStatus, RecorderSnapshot, StreamStatus
from midas_cli.session.folder import STAGING_DIR
from midas_cli.session.reader import Session
from helpers.cli import midas, wait_for as _wait_for
from helpers.net import free_port

META = ("--subject", "1", "--task", "suturing", "--trial", "1")
TRACEBACK = "Traceback (most recent call last)"


def _spawn(out: Path, *extra: str, group: bool = False, faulthandler: bool = False,
           env_extra: dict[str, str] | None = None) -> subprocess.Popen:
    env = {**os.environ, "NO_COLOR": "1", **({"PYTHONFAULTHANDLER": "1"} if faulthandler else {}), **(env_extra or {})}
    return subprocess.Popen([sys.executable, "-m", "midas_cli", "record", "--out", str(out), *META, *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            start_new_session=group)


def _manifest_appeared(out: Path):
    return next(iter(out.glob("*/manifest.json")), None)


def _status(manifest: Path) -> str | None:
    try:
        return json.loads(manifest.read_text())["status"]
    except (OSError, ValueError, KeyError):
        return None


def _sessions(out: Path) -> list[Path]:
    """The session folders in ``out``: every folder but the hidden one where sessions are made."""
    return [p for p in out.iterdir() if p.is_dir() and p.name != STAGING_DIR] if out.exists() else []


def _staging_left(out: Path) -> list[Path]:
    """Session folders a killed start left half made (in ``out/.midas-new``)."""
    return list((out / STAGING_DIR).iterdir()) if (out / STAGING_DIR).is_dir() else []


# Logs every named semaphore (multiprocessing's SemLock: a /dev/shm/sem.mp-* file) that a process creates.
# It watches midas's own processes only: a count of /dev/shm failed whenever another program on the
# machine used multiprocessing meanwhile.
_SEMAPHORE_HOOK = """import os
import _multiprocessing

_Real = _multiprocessing.SemLock


class _LoggedSemLock(_Real):
    def __new__(cls, kind, value, maxvalue, name, unlink, *rest):
        with open(os.environ["MIDAS_TEST_SEMAPHORE_LOG"], "a") as fh:
            fh.write(f"{os.getpid()} {name}\\n")
        return super().__new__(cls, kind, value, maxvalue, name, unlink, *rest)


_multiprocessing.SemLock = _LoggedSemLock
"""


def _semaphore_logging(folder: Path) -> tuple[dict[str, str], Path]:
    """Environment that makes every midas process log the named semaphores it creates, and the log."""
    (folder / "hook").mkdir(parents=True)
    (folder / "hook" / "sitecustomize.py").write_text(_SEMAPHORE_HOOK)
    log = folder / "semaphores.log"
    path = os.pathsep.join(p for p in (str(folder / "hook"), os.environ.get("PYTHONPATH", "")) if p)
    return {"PYTHONPATH": path, "MIDAS_TEST_SEMAPHORE_LOG": str(log)}, log


def _descendants(pid: int) -> set[int]:
    """PIDs of ``pid``'s children, grandchildren, ... (from /proc, this process tree only)."""
    found, frontier = set(), [pid]
    while frontier:
        parent = frontier.pop()
        for task in Path(f"/proc/{parent}/task").glob("*"):
            try:
                children = (task / "children").read_text().split()
            except OSError:
                continue
            for child in map(int, children):
                if child not in found:
                    found.add(child)
                    frontier.append(child)
    return found


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is dead for our purposes
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


# -- 3. signals at any moment --------------------------------------------------------------------
@pytest.mark.parametrize("sig,status", [(signal.SIGINT, "complete"), (signal.SIGHUP, "interrupted")])
@pytest.mark.parametrize("delay_ms", [5, 12, 20])
def test_a_signal_right_after_the_manifest_appears_still_stops_the_recording(tmp_path: Path, sig, status,
                                                                              delay_ms: int) -> None:
    """No --duration: a dropped signal would leave the recorder running until the timeout."""
    process = _spawn(tmp_path, "--simulate", "--no-tui")
    _wait_for(lambda: _manifest_appeared(tmp_path), step_s=0.001)
    time.sleep(delay_ms / 1000)
    process.send_signal(sig)
    try:
        stdout, stderr = process.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        process.kill()
        raise AssertionError(f"{sig.name} {delay_ms} ms after the manifest appeared was ignored") from None
    assert process.returncode == 0, stderr
    assert TRACEBACK not in stderr
    (path,) = _sessions(tmp_path)
    session = Session.open(path)
    assert session.status == status and sig.name in session.manifest["stop_reason"]
    assert midas("session", "verify", str(path)).returncode == 0


@pytest.mark.parametrize("delay_s", [0.25, 0.5, 1.0])
def test_ctrl_c_during_start_up_never_prints_a_traceback(tmp_path: Path, delay_s: float) -> None:
    """Before the session exists: exit 130 and no folder; after: a finalised session. (The first
    few tens of ms belong to the Python interpreter's own start, before any midas code runs.)"""
    process = _spawn(tmp_path, "--simulate", "--no-tui", faulthandler=True)
    time.sleep(delay_s)
    process.send_signal(signal.SIGINT)
    try:
        stdout, stderr = process.communicate(timeout=60)
    except subprocess.TimeoutExpired:  # say where it hangs: faulthandler dumps every thread on SIGABRT
        process.send_signal(signal.SIGABRT)
        stdout, stderr = process.communicate(timeout=30)
        raise AssertionError(f"SIGINT {delay_s} s after start did not end midas record:\n{stderr[-6000:]}") from None
    assert TRACEBACK not in stderr and "KeyboardInterrupt" not in stderr, stderr
    sessions = _sessions(tmp_path)
    if process.returncode == 130:
        assert not sessions and len(stderr.strip().splitlines()) == 1, stderr
    else:
        assert process.returncode == 0, stderr
        (path,) = sessions
        assert Session.open(path).status == "complete"
        assert stdout.strip().splitlines()[-1] == str(path)


# -- 4. no litter, whatever is killed when ------------------------------------------------------
@pytest.mark.slow
def test_twenty_kills_of_the_process_group_leave_nothing_but_repairable_sessions(tmp_path: Path) -> None:
    rng = random.Random(13)
    semaphore_env, semaphore_log = _semaphore_logging(tmp_path)
    for attempt in range(20):
        out = tmp_path / f"kill{attempt}"
        duration = rng.choice(["1", "2"])
        process = _spawn(out, "--simulate", "--duration", duration, "--no-tui", group=True, env_extra=semaphore_env)
        moment = rng.random()
        if moment < 0.3:  # start-up: before or while the workers start
            time.sleep(rng.uniform(0.0, 1.5))
        elif moment < 0.7:  # while recording
            _wait_for(lambda out=out: _manifest_appeared(out), step_s=0.01)
            time.sleep(rng.uniform(0.0, 1.0))
        else:  # around the stop and finalise
            _wait_for(lambda out=out: _manifest_appeared(out), step_s=0.01)
            manifest = _manifest_appeared(out)
            _wait_for(lambda manifest=manifest: _status(manifest) not in ("recording", None), timeout_s=60,
                      step_s=0.002)
            time.sleep(rng.uniform(0.0, 0.05))
        tree = {process.pid} | _descendants(process.pid)
        os.killpg(process.pid, signal.SIGKILL)
        process.communicate(timeout=30)
        _wait_for(lambda tree=tree: not any(_alive(pid) for pid in tree), timeout_s=10, step_s=0.05)
        for path in _sessions(out):
            midas("session", "repair", str(path), check=True)
            verified = midas("session", "verify", str(path))
            assert verified.returncode == 0, (attempt, verified.stdout, verified.stderr)
            assert not list(path.rglob("*.tmp")), list(path.rglob("*.tmp"))
        for staging in _staging_left(out):  # killed while the session folder was made: no data in it
            assert not list(staging.glob("streams/*")), list(staging.rglob("*"))
        if _staging_left(out):  # and the next start there removes it
            midas("record", "--out", str(out), *META, "--simulate", "--duration", "0.5", "--no-tui", check=True)
            assert not _staging_left(out) and not (out / STAGING_DIR).exists()
    assert not semaphore_log.exists(), semaphore_log.read_text()  # pipes only: nothing a kill could leave in /dev/shm


# Kills the process (SIGKILL, as a killed process group would) the moment it gives a new session folder its
# name: its manifest and subfolders are written, the named folder does not exist yet.
_KILL_AT_NAMING_HOOK = """import os
import signal

_real_rename = os.rename


def _rename(src, dst, *args, **kwargs):
    if os.path.basename(os.path.dirname(str(src))) == ".midas-new":
        os.kill(os.getpid(), signal.SIGKILL)
    return _real_rename(src, dst, *args, **kwargs)


os.rename = _rename
"""


def test_a_kill_while_the_session_folder_is_made_leaves_no_session_and_the_next_start_cleans_up(
        tmp_path: Path) -> None:
    (tmp_path / "hook").mkdir()
    (tmp_path / "hook" / "sitecustomize.py").write_text(_KILL_AT_NAMING_HOOK)
    out = tmp_path / "out"
    process = _spawn(out, "--simulate", "--duration", "1", "--no-tui", env_extra={"PYTHONPATH": str(tmp_path / "hook")})
    process.communicate(timeout=120)
    assert process.returncode == -signal.SIGKILL
    assert _sessions(out) == [] and len(_staging_left(out)) == 1  # no half-made session under a session's name
    assert json.loads(midas("session", "list", str(out), "--json").stdout or "[]") == []
    result = midas("record", "--out", str(out), *META, "--simulate", "--duration", "1", "--no-tui", check=True)
    (path,) = _sessions(out)
    assert result.stdout.strip().splitlines()[-1] == str(path) and not (out / STAGING_DIR).exists()
    assert midas("session", "verify", str(path)).returncode == 0


def test_a_killed_recorder_takes_its_workers_with_it(tmp_path: Path) -> None:
    process = _spawn(tmp_path, "--simulate", "--no-tui")
    _wait_for(lambda: any(f.stat().st_size > 2000 for f in tmp_path.glob("*/streams/emht.csv")), step_s=0.05)
    workers = _descendants(process.pid)
    assert workers, "the recorder has no worker processes"
    process.kill()
    process.communicate(timeout=10)
    _wait_for(lambda: not any(_alive(pid) for pid in workers), timeout_s=15, step_s=0.05)


# -- a failed start ------------------------------------------------------------------------------
def test_a_start_that_fails_is_marked_failed_and_hidden_from_lists(tmp_path: Path) -> None:
    url = f"obs://127.0.0.1:{free_port()}?timeout=0.5"
    result = midas("record", "--device", f"video={url}", "--device", "emht=sim://emht", "--duration", "5",
                   "--out", str(tmp_path), *META, "--status-json", timeout=90)
    assert result.returncode == 3, result.stderr
    assert len(result.stderr.strip().splitlines()[-1:]) == 1 and "video" in result.stderr
    objects = [json.loads(line) for line in result.stdout.splitlines()]  # JSON lines only
    final = objects[-1]
    assert final["event"] == "stopped" and final["status"] == "failed"
    (path,) = _sessions(tmp_path)
    assert final["session_path"] == str(path)
    assert json.loads((path / "manifest.json").read_text())["status"] == "failed"
    listed = midas("session", "list", str(tmp_path), "--json", check=True)
    assert json.loads(listed.stdout) == []
    listed_all = midas("session", "list", str(tmp_path), "--json", "--all", check=True)
    assert [s["status"] for s in json.loads(listed_all.stdout)] == ["failed"]


def test_a_start_that_fails_still_ends_stdout_with_the_session_path(tmp_path: Path) -> None:
    """`path=$(midas record ... | tail -n 1)` finds the folder however recording ends (issue 23 item 6)."""
    url = f"obs://127.0.0.1:{free_port()}?timeout=0.5"
    result = midas("record", "--device", f"video={url}", "--device", "emht=sim://emht", "--duration", "60",
                   "--out", str(tmp_path), *META, "--no-tui", timeout=120)  # the failed open ends it
    assert result.returncode == 3, result.stderr
    (path,) = _sessions(tmp_path)
    assert result.stdout.splitlines()[-1] == str(path)


def test_a_full_disk_at_the_start_leaves_no_folder(tmp_path: Path) -> None:
    """RLIMIT_FSIZE makes the first write past a few bytes fail with EFBIG, as a full disk would."""
    import resource

    def tiny_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (64, 64))

    result = midas("record", "--simulate", "--duration", "2", "--out", str(tmp_path), *META, "--no-tui",
                   timeout=60, preexec_fn=tiny_files)
    assert result.returncode == 4, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and TRACEBACK not in result.stderr
    assert _sessions(tmp_path) == []


# -- 5. scripts, and 6. the end-of-run summary after an outage ---------------------------------
def _rows_in(out: Path, stream: str) -> int:
    files = list(out.glob(f"*/streams/{stream}.csv"))
    return files[0].read_bytes().count(b"\n") - 1 if files else 0


@pytest.fixture(scope="module")
def outage_session(tmp_path_factory) -> tuple[subprocess.CompletedProcess, Path]:
    """A recording with `--status-json` (stderr a pipe) during which the pedal board is unplugged
    for a second, then stopped with SIGINT: every step waits for what the recorder wrote, not a clock."""
    tmp = tmp_path_factory.mktemp("outage")
    out, link = tmp / ("sessions-with-a-long-name-" * 4), tmp / "fps-port"
    with FpsEmulator(FpsEmulatorConfig(channels=9, link=link)) as emulator:
        process = _spawn(out, "--simulate", "--device", f"fps=fps://{link}?rate=200", "--status-json")
        _wait_for(lambda: _rows_in(out, "fps") > 200, step_s=0.05)
        emulator.set_unplugged(True)
        time.sleep(1.0)
        emulator.set_unplugged(False)
        rows = _rows_in(out, "fps")
        _wait_for(lambda: _rows_in(out, "fps") > rows + 200, step_s=0.05)
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=60)
    result = subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)
    assert result.returncode == 0, stderr
    return result, out


def test_status_json_is_json_lines_only_ending_with_the_stopped_object(outage_session) -> None:
    result, _out = outage_session
    objects = [json.loads(line) for line in result.stdout.splitlines()]  # every line is JSON
    assert all(o["event"] == "status" for o in objects[:-1]) and len(objects) >= 2
    final = objects[-1]
    assert final["event"] == "stopped" and final["status"] == "complete" and "SIGINT" in final["reason"]
    manifest = Session.open(Path(final["session_path"])).manifest
    for name, counts in final["streams"].items():
        entry = manifest["streams"][name]
        assert counts["samples"] == entry["samples"]
        assert counts["missing"] == entry["seq_gaps"]["missing"]
    fps = final["streams"]["fps"]
    assert fps["missing_outage"] > 0 and fps["reconnects"] == 1 and fps["missing_unexplained"] == 0
    assert any(p.startswith("fps:") and "outage" in p for p in final["problems"])
    assert not any(p.startswith(("emht:", "video:", "handkp:")) for p in final["problems"])


def test_the_summary_says_what_went_wrong_on_unfolded_lines(outage_session) -> None:
    result, _out = outage_session
    lines = result.stderr.splitlines()
    title = next(line for line in lines if ": complete (stopped by the operator" in line)
    assert title.strip().startswith("suturing_S1_T1_")
    fps_row = next(line for line in lines if line.strip("│ ").startswith("fps "))
    final = json.loads(result.stdout.splitlines()[-1])["streams"]["fps"]
    assert f"{final['missing_outage']} / 0" in fps_row  # missing (outage / other)
    problems = [line for line in lines if line.startswith("problems:")]
    assert len(problems) == 1 and "fps:" in problems[0] and "reconnected 1 time" in problems[0]


def test_messages_to_a_non_terminal_stderr_are_never_folded(tmp_path: Path) -> None:
    deep = tmp_path / ("a-rather-long-folder-name-" * 4) / ("another-long-part-" * 4)
    result = midas("record", "--rig", str(deep / "no-such-rig.toml"), "--out", str(tmp_path), *META)
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1 and "no-such-rig.toml" in result.stderr


# -- 6. the operator's eye -----------------------------------------------------------------------
def test_duration_counts_from_the_session_start(tmp_path: Path) -> None:
    result = midas("record", "--simulate", "--duration", "3", "--out", str(tmp_path), *META, "--status-json",
                   timeout=90, check=True)
    objects = [json.loads(line) for line in result.stdout.splitlines()]
    manifest = Session.open(Path(objects[-1]["session_path"])).manifest
    length_s = (manifest["stop"]["host_ns"] - manifest["start"]["host_ns"]) / 1e9
    assert abs(length_s - 3.0) <= 0.5, length_s
    elapsed = [o["elapsed_s"] for o in objects[:-1]]
    assert elapsed == sorted(elapsed) and elapsed[-1] <= 3.5
    assert objects[-1]["duration_s"] == pytest.approx(length_s, abs=0.01)


def test_a_normal_recording_logs_no_error(tmp_path: Path) -> None:
    result = midas("record", "--simulate", "--duration", "2", "--out", str(tmp_path), *META, "--no-tui",
                   timeout=90, check=True)
    assert "ERROR" not in result.stderr and "did not exit" not in result.stderr, result.stderr
    log = (Path(result.stdout.splitlines()[-1]) / "logs" / "midas.log").read_text()
    assert " ERROR " not in log, log


def _snapshot(state: str, age_s: float, labels: dict[str, str]) -> RecorderSnapshot:
    emht = StreamStatus("emht", 240.0, None, 100, age_s, 0, 0, 0,
                        {"s1_x_mm": 12.5, "s1_y_mm": 1.0, "s1_z_mm": 2.0})
    fps = StreamStatus("fps", 250.0, 250.0, 100, 0.01, 0, 0, 0,
                       {"ch1_adc": 500, "ch1_pressed": 1, "ch2_adc": 10, "ch2_pressed": 0})
    marker = StreamStatus("video_marker", None, None, 1, 30.0, 0, 0, 0)
    devices = (DeviceStatus("emht", "emht", "sim://emht", state, 1, "gone", (emht,)),
               DeviceStatus("fps", "fps", "sim://fps", "ok", 0, "", (fps,), labels),
               DeviceStatus("video", "video", "obs://", "ok", 0, "", (marker,)))
    return RecorderSnapshot("/s", "s", 5.0, None, 10**9, 0.0, 0, devices)


def _render(snapshot: RecorderSnapshot) -> str:
    console = Console(width=120, record=True, file=open(os.devnull, "w"))
    console.print(dashboard(snapshot))
    return console.export_text()


def test_the_screen_marks_stale_values_and_names_the_pedals() -> None:
    live = _render(_snapshot("ok", 0.01, {"1": "clutch", "2": "camera"}))
    assert "STALE" not in live and "12.5" in live
    assert re.search(r"clutch\s+█", live) and "camera" in live and "P1" not in live
    lost = _render(_snapshot("lost", 4.2, {}))
    assert "STALE 4.2 s, lost" in lost and "P1" in lost
    assert re.search(r"video_marker.*events", lost)  # an event stream has no rate to fall short of


# -- 8. option values ----------------------------------------------------------------------------
@pytest.mark.parametrize("args,words", [
    (("--simulate", "--duration", "nan"), "--duration"),
    (("--simulate", "--duration", "inf"), "--duration"),
    (("--simulate", "--seed", "-1"), "--seed"),
    (("--simulate", "--master-rate", "0"), "--master-rate"),
    (("--device", "a/b=sim://emht", "--duration", "1"), "device name"),
    (("--device", "../x=sim://emht", "--duration", "1"), "device name"),
])
def test_impossible_option_values_are_refused_before_anything_is_created(tmp_path: Path, args, words) -> None:
    out = tmp_path / "out"
    result = midas("record", *args, "--out", str(out), *META, timeout=60)
    assert result.returncode == 2, (result.returncode, result.stderr)
    assert len(result.stderr.strip().splitlines()) == 1 and words in result.stderr
    assert _sessions(out) == []
