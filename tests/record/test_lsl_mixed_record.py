"""A mixed `midas record`: simulated EmHT, the FPS board emulator, the Raven emulator, an LSL outlet and
the simulated RGB-D camera in one session that `midas session verify` accepts."""

from __future__ import annotations

from pathlib import Path

import pytest

from midas_cli.devices.raven.emulator import RavenEmulator, RavenEmulatorConfig
from midas_cli.session.reader import Session
from helpers.cli import midas, record_until
from helpers.lsl_fixture import CounterOutlet, loopback_lsl_config
from helpers.net import free_udp_port

pytest.importorskip("pylsl", reason="pylsl (pip install pylsl==1.18.6) is not installed")
fps_emulator = pytest.importorskip("midas_cli.devices.fps.emulator", reason="no FPS emulator in this tree")


def test_mixed_session_verifies(tmp_path: Path) -> None:
    loopback_lsl_config(tmp_path)
    port = free_udp_port()
    with fps_emulator.FpsEmulator(fps_emulator.FpsEmulatorConfig(channels=9)) as board, \
            RavenEmulator(RavenEmulatorConfig("127.0.0.1", port, rate_hz=200)), \
            CounterOutlet("midas-test-mixed", rate=50.0):
        streams = ("emht", "fps", "raven", "hr", "hr_clock", "rgbd", "rgbd_truth")
        result = record_until(tmp_path / "sessions",
                              ["--device", "emht=sim://emht?rate=120", "--device", f"fps=fps://{board.path}?rate=100",
                               "--device", f"raven=raven://127.0.0.1:{port}?rate=200",
                               "--device", "hr=lsl://?name=midas-test-mixed", "--device", "rgbd=sim://rgbd?rate=5",
                               "--subject", "2", "--task", "mixed", "--trial", "1", "--no-tui"],
                              {name: 3 for name in streams})
    assert result.returncode == 0, result.stderr
    path = Path(result.stdout.strip().splitlines()[-1])
    verify = midas("session", "verify", str(path))
    assert verify.returncode == 0, verify.stdout + verify.stderr
    session = Session.open(path)
    assert set(session.stream_names) == {*streams, "events"}  # events: the operator's markers (none here)
    assert all(session.manifest["streams"][name]["samples"] > 0 for name in streams)
    assert session.manifest["status"] == "complete"
