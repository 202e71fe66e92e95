"""LSL: a stream published by the test is recorded by `midas record`, with clock-offset probes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from midas_cli.devices.lsl.device import predicate
from midas_cli.errors import ConfigError
from midas_cli.session.reader import Session
from helpers.cli import midas, record_until
from helpers.lsl_fixture import CounterOutlet, loopback_lsl_config

pytest.importorskip("pylsl", reason="pylsl (pip install pylsl==1.18.6) is not installed")


@pytest.fixture(scope="module", autouse=True)
def loopback_only(tmp_path_factory: pytest.TempPathFactory) -> None:
    loopback_lsl_config(tmp_path_factory.mktemp("lsl"))


def test_predicate_needs_a_property_and_refuses_quotes() -> None:
    assert predicate({"name": "HR", "type": "ECG", "source_id": "", "hostname": ""}, "u") == "name='HR' and type='ECG'"
    with pytest.raises(ConfigError, match="say which LSL stream"):
        predicate({"name": "", "type": "", "source_id": "", "hostname": ""}, "lsl://")
    with pytest.raises(ConfigError, match="quotes"):
        predicate({"name": "a'b", "type": "", "source_id": "", "hostname": ""}, "u")


def test_missing_stream_is_a_clear_device_error(tmp_path: Path) -> None:
    result = midas("record", "--device", "x=lsl://?name=nobody-sends-this&timeout=0.5", "--duration", "1",
                   "--subject", "1", "--task", "lsl", "--trial", "1", "--out", str(tmp_path), "--no-tui")
    assert result.returncode == 3
    assert "no LSL stream matches name='nobody-sends-this' within 0.5 s" in result.stderr


def test_record_an_lsl_outlet(tmp_path: Path) -> None:
    with CounterOutlet("midas-test-counter", rate=100.0) as outlet:
        result = record_until(tmp_path, ["--device", "hr=lsl://?name=midas-test-counter&type=Test", "--subject", "1",
                                         "--task", "lsl", "--trial", "1", "--no-tui"], {"hr": 300, "hr_clock": 3})
    assert result.returncode == 0, result.stderr
    session_path = Path(result.stdout.strip().splitlines()[-1])
    verify = midas("session", "verify", str(session_path))
    assert verify.returncode == 0, verify.stdout + verify.stderr
    session = Session.open(session_path)
    frame = session.read_stream("hr")
    assert list(frame.columns) == ["seq", "t_host_ns", "t_lsl_s", "counter", "sine", "cosine"]
    counter = frame["counter"].to_numpy().astype(int)
    assert len(frame) >= 250 and np.array_equal(counter, np.arange(counter[0], counter[0] + len(frame)))
    pushed = dict(outlet.pushed)
    assert np.allclose(frame["t_lsl_s"], [pushed[k] for k in counter], atol=1e-6)  # sender times kept raw
    assert np.allclose(frame["sine"], np.sin(counter / 10), atol=1e-6)
    probes = session.read_stream("hr_clock")
    assert len(probes) >= 3 and np.all(np.abs(probes["offset_s"]) < 0.005)  # one host: offset ~ 0
    anchor = session.manifest["clock"]["anchor_ns"]
    assert np.allclose(probes["local_clock_s"] * 1e9 + anchor, probes["t_host_ns"], atol=1e3)
    device = json.loads((session_path / "manifest.json").read_text())["devices"]["hr"]
    assert device["kind"] == "lsl" and device["settings"]["channels"] == 3
