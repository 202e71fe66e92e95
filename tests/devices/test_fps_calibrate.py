"""`midas calibrate fps`: the interactive procedure answered by a test while the emulator presses the
requested pedal, the --session form, and the rig-file edit."""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path

import numpy as np
import pexpect
import pytest

from midas_cli.clock import HostClock
from midas_cli.devices.fps.driver import fps_stream_spec
from midas_cli.devices.fps.emulator import FpsEmulator, FpsEmulatorConfig
from midas_cli.devices.fps.rigfile import load_target, write_target
from midas_cli.devices.pedals import PedalThresholds
from midas_cli.devices.rigconfig import load_rig
from midas_cli.errors import ConfigError
from midas_cli.session.writer import SessionMetadata, SessionWriter
from helpers.cli import REPO, midas

RIG = """# test console
[rig]
name = "test"
platform = "davinci-xi"

[devices.fps]   # the pedal board
url = "{url}"
pedals = {{ 2 = "secondary_energy_right", 4 = "primary_energy_right", 6 = "camera" }}

[devices.video]
url = "sim://video?rate=30"
"""


def _thresholds(rig: Path) -> tuple[list[float], list[float]]:
    url = load_rig(rig).devices["fps"].url
    params = dict(part.split("=") for part in url.split("?")[1].split("&"))
    return [float(v) for v in params["press_v"].split(",")], [float(v) for v in params["release_v"].split(",")]


def test_interactive_calibration_against_the_emulator(tmp_path: Path) -> None:
    rig = tmp_path / "rig.toml"
    with FpsEmulator(FpsEmulatorConfig(channels=9, pedals="idle", press_counts=700)) as emulator:
        rig.write_text(RIG.format(url=f"fps://{emulator.path}?rate=200"))
        env = {**os.environ, "NO_COLOR": "1", "COLUMNS": "120", "TERM": "xterm"}
        child = pexpect.spawn(sys.executable, ["-m", "midas_cli", "calibrate", "fps", "--rig", str(rig),
                                               "--rest-s", "1", "--press-s", "1"], env=env, cwd=str(REPO),
                              timeout=120, encoding="utf-8")
        child.expect("measure the rest level")
        child.sendline("")
        asked = []
        while child.expect([r"Channel (\d) = (\w+): press Enter", pexpect.EOF]) == 0:
            channel = int(child.match.group(1))
            asked.append(channel)
            emulator.force(channel, True)
            child.sendline("")
            child.expect("Release")
            emulator.force(channel, False)
        child.close()
    assert child.exitstatus == 0, child.before
    assert asked == [2, 4, 6]
    press, release = _thresholds(rig)
    rest_v, pressed_v = emulator._rest * 5 / 1023, 700 * 5 / 1023
    for c in (2, 4, 6):
        assert rest_v[c - 1] + 0.3 < release[c - 1] < press[c - 1] < pressed_v - 0.3
    assert [press[c - 1] for c in (1, 3, 5, 7, 8, 9)] == [1.5] * 6  # unmapped channels keep theirs
    text = rig.read_text()
    assert "# the pedal board" in text and 'url = "sim://video?rate=30"' in text


def _pedal_session(root: Path) -> Path:
    """A recorded board: channel 4 pressed (600 counts) 20 % of the time, channel 6 never pressed."""
    spec = fps_stream_spec("fps", 9, 250.0)
    clock = HostClock.anchored_now()
    writer = SessionWriter.create(root, SessionMetadata("1", "pedals", 1), clock, {"fps": {"kind": "fps"}}, [spec])
    rng = np.random.default_rng(0)
    n = 2500
    adc = np.clip(20 + rng.normal(0, 2, (n, 9)), 0, 1023).astype(int)
    pressed = (np.arange(n) // 250) % 5 == 1
    adc[pressed, 3] = 600 + rng.integers(-20, 20, int(pressed.sum()))
    t0 = clock.now_ns()
    rows = [(i, t0 + i * 4_000_000, i * 4000, *adc[i], *([0] * 9)) for i in range(n)]
    writer.append("fps", spec.format_rows(rows))
    writer.finalize("complete", "test", t0 + n * 4_000_000, {})
    return writer.folder


def test_calibration_from_a_recorded_session(tmp_path: Path) -> None:
    session = _pedal_session(tmp_path / "sessions")
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG.format(url="fps:///dev/ttyACM0?rate=250&press_v=2.5&release_v=2.0"))
    result = midas("calibrate", "fps", "--session", str(session), "--rig", str(rig), "--json")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["flagged"] == [2, 6]
    ch4 = next(c for c in report["channels"] if c["channel"] == 4)
    assert 20 * 5 / 1023 < ch4["release_v"] < ch4["press_v"] < 580 * 5 / 1023
    press, release = _thresholds(rig)
    assert (press[3], release[3]) == (ch4["press_v"], ch4["release_v"])
    assert (press[5], release[5]) == (2.5, 2.0)  # flagged: unchanged
    assert "does not separate" in result.stderr


def test_rig_file_is_created_and_a_missing_url_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="give --url"):
        load_target(tmp_path / "new.toml", "fps", None)
    target = load_target(tmp_path / "new.toml", "fps", "fps:///dev/ttyACM0?channels=5")
    assert target.pedals == {1: "secondary_energy_left", 2: "secondary_energy_right", 3: "primary_energy_left",
                             4: "primary_energy_right", 5: "clutch"}
    url = write_target(target, PedalThresholds.uniform(5, 2.0, 1.2))
    assert re.search(r"press_v=2\.000(,2\.000){4}&release_v=1\.200", url)
    assert load_rig(tmp_path / "new.toml").devices["fps"].url == url
