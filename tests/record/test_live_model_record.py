"""`midas record --live-model`, end to end through the CLI: a small causal model trained on simulated
sessions recognises a replayed session live; the session keeps ``gestures_live``, one row per frame of
the model's clock but the frames it says it skipped, and its classes are the offline causal model's on
the same frames. A model the rig cannot feed is refused before anything exists; the live screen shows
the current gesture."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from midas_cli.record.control import send_request
from midas_cli.session.reader import Session
from helpers.cli import midas, record_until, stream_rows
from helpers.lsl_fixture import loopback_lsl_config

pytestmark = pytest.mark.slow
META = ("--subject", "1", "--task", "suturing", "--trial", "9")
FRAMES = 90  # gestures_live rows to wait for (3 s at the model's 30 Hz)


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(a labelled simulated session, a causal MS-TCN++ run trained on EmHT of three such sessions, labelling
    each frame 0.2 s late: --delay, so the recording's end must label its last frames)."""
    root = tmp_path_factory.mktemp("live")
    midas("simulate", "dataset", "--platform", "davinci-xi", "--trials", "3", "--max-seconds", "20", "--seed", "3",
          "--out", str(root / "sim"), check=True)
    sessions = sorted(p for p in (root / "sim").iterdir() if (p / "manifest.json").exists())
    midas("align", *map(str, sessions), check=True, timeout=300)
    midas("train", "gestures", str(root / "sim"), "--model", "mstcn", "--causal", "--delay", "0.2", "--modalities", "emht", "--epochs", "3",
          "--out", str(root / "run"), check=True, timeout=600)
    return sessions[0], root / "run"


def _replay(session: Path) -> subprocess.Popen:
    env = {**os.environ, "NO_COLOR": "1"}
    return subprocess.Popen([sys.executable, "-m", "midas_cli", "replay", str(session), "--to", "lsl", "--streams",
                             "emht", "--loop", "--delay", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)


def test_live_gestures_from_a_replay_equal_the_offline_causal_models(trained, tmp_path: Path) -> None:
    from midas_cli.analysis.live_gestures import load_live_model, offline_predictions

    loopback_lsl_config(tmp_path)
    source, run = trained
    spec = load_live_model(run).spec
    control = tmp_path / "ctl.sock"
    status: list[dict] = []

    def enough_and_asked(out: Path) -> bool:  # `midas ctl status` (its request) once frames are predicted
        if stream_rows(out, "gestures_live") < FRAMES:
            return False
        status.append(send_request(control, {"cmd": "status"}))
        return True

    player = _replay(source)
    try:
        result = record_until(tmp_path / "out", [
            "--device", f"emht=lsl://?source_id=midas:{source.name}:emht&timeout=30", "--live-model", str(run),
            "--control", str(control), *META, "--no-tui"], until=enough_and_asked, timeout=240)
    finally:
        player.send_signal(signal.SIGINT)
        player.communicate(timeout=30)
    assert result.returncode == 0, result.stderr
    session = Session.open(result.stdout.strip().splitlines()[-1])
    entry = session.manifest["streams"]["gestures_live"]
    live = entry["live_model"]
    assert (live["run_id"], live["checkpoint_sha256"], live["model"]) == (spec.run_id, spec.checkpoint_sha256, spec.model)
    assert live["rate_hz"] == spec.rate_hz and live["input_rows_dropped"] == 0
    assert (live["delay_frames"], live["delay_s"]) == (6, 0.2)  # 0.2 s at the model's 30 Hz

    rows = session.read_stream("gestures_live")
    seq, times = rows["seq"].to_numpy(np.int64), rows["t_host_ns"].to_numpy(np.int64)
    steps = np.diff(seq)
    assert len(rows) >= FRAMES and (steps >= 1).all()
    assert int((steps - 1).sum()) <= live["frames_skipped"]  # a row per frame but those it said it skipped
    assert np.abs(np.diff(times) - steps * 1e9 / spec.rate_hz).max() <= 1  # on the model's frame clock
    assert (rows["t_pred_ns"].to_numpy(np.int64) >= times).all()
    assert set(rows["class"]) <= set(spec.classes)

    assert live["nominal_rates_hz"] == {"emht": session.stream_spec("emht").nominal_rate_hz}
    offline = offline_predictions(session.path, run, times, live["nominal_rates_hz"])
    agree = slice(None) if live["frames_skipped"] == 0 else slice(0, int(np.argmax(steps > 1)) + 1)
    assert [p.label for p in offline][agree] == rows["class"].tolist()[agree]
    assert [p.seq for p in offline][agree] == seq.tolist()[agree]
    # the decoded class (the run's clean-up, decided at once: --decode-lag 0) is the offline decoding's too
    decoding = live["decoding"]
    assert decoding["min_segment_frames"] > 1 and decoding["gesture_order"] and decoding["lag_frames"] == 0
    assert [p.decoded for p in offline][agree] == rows["decoded"].tolist()[agree]
    assert (rows["t_decoded_ns"].to_numpy(np.int64) >= rows["t_pred_ns"].to_numpy(np.int64)).all()

    evaluated = json.loads(midas("eval", "live", str(session.path), "--run", str(run), "--json", check=True,
                                 timeout=300).stdout)[0]
    assert {(a["prediction"], a["reference"]) for a in evaluated["agreements"]} >= {("class", "offline"),
                                                                                    ("decoded", "offline")}
    for offline_agreement in (a for a in evaluated["agreements"] if a["reference"] == "offline"):
        assert evaluated["frames"] == len(rows) and offline_agreement["frames"] == len(rows)
        if live["frames_skipped"] == 0:
            assert offline_agreement["accuracy"] == 1.0 and offline_agreement["edit"] == 100.0
            assert offline_agreement["detected"] == offline_agreement["segments"]
            assert offline_agreement["delay_ms"]["max"] == 0

    gesture = status[0]["gesture"]
    assert status[0]["ok"] and gesture["label"] in spec.classes and 0 <= gesture["probability"] <= 1
    assert gesture["latency_ms"] >= 0 and gesture["duration_s"] > 0
    assert midas("session", "verify", str(session.path)).returncode == 0


def test_a_model_the_rig_cannot_feed_is_refused_before_anything_is_recorded(trained, tmp_path: Path) -> None:
    _, run = trained
    rig = tmp_path / "rig.toml"
    shutil.copytree(run, tmp_path / "runs" / "r1")
    rig.write_text('[rig]\nname = "pedals only"\nplatform = "davinci-xi"\n[devices.fps]\nurl = "sim://fps"\n'
                   '[live]\nmodel = "runs/r1"\n', encoding="utf-8")  # relative to the rig file
    result = midas("record", "--rig", str(rig), "--duration", "5", "--out", str(tmp_path / "out"), *META, "--no-tui")
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "stream emht" in lines[0] and str(tmp_path / "runs" / "r1") in lines[0], lines
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


@pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux is not installed (.ci/run installs it)")
def test_the_live_screen_shows_the_current_gesture(trained, tmp_path: Path) -> None:
    """80x24: the simulated rig's EmHT feeds the model; the gesture line and every pedal fit."""
    _, run = trained
    name = f"midas-test-live-{os.getpid()}"
    command = (f"{sys.executable} -m midas_cli record --simulate --duration 60 --out {tmp_path} "
               f"--live-model {run} {' '.join(META)}")
    subprocess.run(["tmux", "-L", name, "new-session", "-d", "-s", name, "-x", "80", "-y", "24", command], check=True)
    try:
        screen = _wait_for_screen(name, lambda text: "gesture G" in text and "P9" in text)
        line = next(line for line in screen.splitlines() if line.startswith("gesture "))
        from midas_cli.analysis.live_gestures import load_live_model

        assert line.split()[1] in load_live_model(run).spec.classes and (" p 0." in line or " p 1.00" in line)
        lines = screen.splitlines()
        top = next(i for i, text in enumerate(lines) if text.startswith("● REC elapsed"))  # under the socket's line
        assert "latency" in line and max(len(text) for text in lines[top:]) <= 80, screen
        subprocess.run(["tmux", "-L", name, "send-keys", "-t", name, "C-c"], check=True)
        _wait_for_screen(name, lambda _: _status(tmp_path) == "complete")
        rows = Session.open(next(p for p in tmp_path.iterdir() if p.is_dir())).read_stream("gestures_live")
        assert len(rows) > 0
    finally:
        subprocess.run(["tmux", "-L", name, "kill-session", "-t", name], capture_output=True)


def _status(out: Path) -> str | None:
    folders = [p for p in out.iterdir() if p.is_dir()]
    return Session.open(folders[0], allow_failed=True).status if folders else None


def _wait_for_screen(name: str, ok, timeout_s: float = 90) -> str:
    """The first screen for which ``ok(screen)`` is true within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    screen = ""
    while time.monotonic() < deadline:
        time.sleep(0.5)
        screen = subprocess.run(["tmux", "-L", name, "capture-pane", "-p", "-J", "-t", name], capture_output=True,
                                text=True).stdout
        if ok(screen):
            return screen
    raise AssertionError(f"never seen on the screen:\n{screen}")
