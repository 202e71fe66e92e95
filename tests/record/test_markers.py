"""Markers and remote control (issue 15 item 5): `midas mark`, `midas ctl`, the events stream, text columns."""

from __future__ import annotations

import json
import os
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from midas_cli.clock import HostClock
from midas_cli.commands.record_keys import MarkerPrompt
from midas_cli.errors import ConfigError, SessionError
from midas_cli.record.control import ControlServer, send_request
from midas_cli.record.markers import events_spec
from midas_cli.session.reader import Session
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
from midas_cli.session.values import parse_stream_bytes
from midas_cli.session.writer import SessionMetadata, SessionWriter
from helpers.cli import midas

META = ("--subject", "1", "--task", "suturing", "--trial", "1")


def _wait(what: str, found, timeout_s: float = 90):
    """``found()``'s first truthy value within ``timeout_s`` (generous: CI machines are busy)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = found()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"{what} did not happen within {timeout_s} s")


def _ctl(env: dict[str, str], *args: str) -> dict:
    result = midas(*args, env=env)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def test_mark_and_ctl_drive_an_armed_recording_through_the_cli(tmp_path: Path) -> None:
    runtime = tmp_path / "run"
    runtime.mkdir(mode=0o700)
    env = {"XDG_RUNTIME_DIR": str(runtime)}
    out = tmp_path / "sessions"

    nobody = midas("mark", "too early", env=env)  # no recorder running: one line, exit 4 (session/data)
    assert nobody.returncode == 4 and nobody.stderr.count("\n") == 1 and "no recording is running" in nobody.stderr

    process = subprocess.Popen([sys.executable, "-m", "midas_cli", "record", "--simulate", "--armed", "--no-tui",
                                "--out", str(out), *META], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, **env, "NO_COLOR": "1"})
    try:
        sock = _wait("the control socket", lambda: next((runtime / "midas").glob("record-*.sock"), None))
        assert sock.name == f"record-{process.pid}.sock"
        assert stat.S_ISSOCK(sock.lstat().st_mode) and stat.S_IMODE(sock.lstat().st_mode) == 0o600
        _wait("the session", lambda: midas("ctl", "status", env=env).returncode == 0)
        assert _ctl(env, "ctl", "status")["state"] == "armed"
        first = _ctl(env, "mark", "warm-up note")["marker"]  # found without a path: the one running recording
        started = _ctl(env, "ctl", "start")
        assert started["state"] == "recording"
        refused = midas("ctl", "start", env=env)  # twice: refused with the recorder's reason, exit 2
        assert refused.returncode == 2 and "already started" in refused.stderr
        second = _ctl(env, "ctl", "--control", str(sock), "mark", 'needle in, "bite" 2')["marker"]
        status = _ctl(env, "ctl", "status")
        assert status["state"] == "recording" and status["markers"] == 3 and status["duration_s"] >= 0
        assert set(status["devices"]) == {"emht", "fps", "video", "handkp"}
        assert status["session_path"] == started["session_path"]
        stopped = _ctl(env, "ctl", "stop")  # returns once the manifest is final
        assert stopped["status"] == "complete" and "ctl stop" in stopped["stop_reason"]
        assert process.wait(timeout=60) == 0
    finally:
        if process.poll() is None:
            process.kill()
        process.communicate()
    assert not sock.exists(), "the socket is removed when the recording ends"

    session = Session.open(stopped["session_path"])
    events = session.read_stream("events")
    assert list(events["text"]) == ["warm-up note", "start", 'needle in, "bite" 2']
    assert list(events["source"]) == ["mark", "ctl", "ctl"]
    assert list(events["seq"]) == [0, 1, 2]
    times = events["t_host_ns"].tolist()
    assert times[0] == first["t_host_ns"] and times[2] == second["t_host_ns"]
    assert session.manifest["start"]["host_ns"] < times[0] < times[1] < times[2] < session.manifest["stop"]["host_ns"]
    assert session.manifest["control"]["started_host_ns"] == times[1] == started["started_host_ns"]
    entry = session.manifest["streams"]["events"]
    assert entry["timing"] == "events" and entry["nominal_rate_hz"] is None and entry["samples"] == 3
    assert [c["dtype"] for c in entry["columns"]] == ["int", "int", "text", "text"]
    assert midas("session", "verify", str(session.path)).returncode == 0
    after = midas("ctl", "status", env=env)
    assert after.returncode == 4 and "no recording is running" in after.stderr


def test_a_control_path_that_is_not_a_stale_socket_is_refused_before_recording(tmp_path: Path) -> None:
    taken = tmp_path / "ctl"
    taken.write_text("not a socket")
    result = midas("record", "--simulate", "--duration", "1", "--control", str(taken), "--out", str(tmp_path / "s"),
                   *META)
    assert result.returncode == 2 and "is not a socket" in result.stderr
    assert taken.read_text() == "not a socket" and not (tmp_path / "s").exists()


def test_control_server_replaces_a_stale_socket_refuses_a_live_one_and_cleans_up(tmp_path: Path) -> None:
    path = tmp_path / "c.sock"
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(path))
    stale.close()  # the file stays, nobody listens: what a killed recorder leaves
    with ControlServer(path) as server:
        server.serve(lambda request: {"echo": request["cmd"]})
        assert stat.S_IMODE(path.lstat().st_mode) == 0o600
        assert send_request(path, {"cmd": "hello"}) == {"ok": True, "echo": "hello"}
        with pytest.raises(ConfigError, match="in use"):
            ControlServer(path)
    assert not path.exists()
    with pytest.raises(SessionError, match="no recording is running"):
        send_request(path, {"cmd": "status"})
    with pytest.raises(ConfigError, match="at most 107"):
        ControlServer(tmp_path / ("x" * 120))


def test_marker_keys_type_cancel_and_ignore_arrow_keys() -> None:
    prompt = MarkerPrompt()
    assert prompt.feed(b"xq") == [] and prompt.text is None  # only m opens the prompt
    assert prompt.feed(b"m") == [] and prompt.text == ""
    assert prompt.feed("ab\x1b[Dc\x7fdé".encode()) == [] and prompt.text == "abdé"
    assert prompt.feed(b"\r") == ["abdé"] and prompt.text is None
    prompt.feed(b"mgone")
    assert prompt.feed(b"\x1b") == [] and prompt.text is None  # a lone Esc cancels
    assert prompt.feed(b"m  \r") == []  # nothing typed: no marker


def test_text_columns_are_quoted_parsed_strictly_and_exported(tmp_path: Path) -> None:
    spec = events_spec()
    clock = HostClock.anchored_now()
    writer = SessionWriter.create(tmp_path, SessionMetadata("1", "demo", 1), clock, {}, [spec])
    t0 = clock.now_ns()
    rows = [(0, t0, 'comma, "quote"', "key"), (1, t0 + 1000, "ünïcode", "mark"), (2, t0 + 2000, None, "ctl")]
    writer.append("events", spec.format_rows(rows))
    writer.finalize("complete", "test", t0 + 10_000, {})
    session = Session.open(writer.folder)
    frame = session.read_stream("events")
    assert frame["text"].tolist()[:2] == ['comma, "quote"', "ünïcode"] and frame["text"].isna().tolist()[2]
    assert session.read_columns("events")["text"].tolist() == ['comma, "quote"', "ünïcode", ""]
    assert midas("session", "verify", str(writer.folder)).returncode == 0
    result = midas("export", str(writer.folder), "--format", "parquet,xdf,mcap", "--out", str(tmp_path / "x"))
    assert result.returncode == 0, result.stderr
    import pandas as pd
    import pyxdf

    parquet = pd.read_parquet(tmp_path / "x" / writer.folder.name / "events.parquet")
    assert parquet["source"].tolist() == ["key", "mark", "ctl"]
    streams, _ = pyxdf.load_xdf(str(tmp_path / "x" / f"{writer.folder.name}.xdf"), synchronize_clocks=False)
    # as LabRecorder would record `midas replay`: a Markers stream, one string channel, the text
    assert streams[0]["info"]["type"] == ["Markers"] and streams[0]["info"]["channel_count"] == ["1"]
    assert [row[0] for row in streams[0]["time_series"]] == ['comma, "quote"', "ünïcode", ""]

    text_spec = StreamSpec("t", "d", (SEQ, T_HOST, Column("text", "text")), None)
    header = text_spec.header_line().encode()
    for bad in (b'0,1,"a"b"\n', b"0,1,unquoted\n", b'0,"1","a"\n', b'0,1,"tab\there"\n'):
        with pytest.raises(SessionError, match="line 2"):
            parse_stream_bytes(header + bad, text_spec, Path("t.csv"))
    with pytest.raises(ValueError, match="control characters"):
        text_spec.format_rows([(0, 1, "two\nlines")])
