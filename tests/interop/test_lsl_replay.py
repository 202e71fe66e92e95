"""`midas replay --to lsl` and `midas record --lsl-out`, through real liblsl on this host only.

Round trip: a session replayed as LSL outlets is recorded back with `lsl://` inlets (both CLIs, end to
end); the values come back equal and the timestamps keep the recorded spacing. Live: `record --lsl-out`
publishes rows that equal the CSV's, with the manifest's labels and units.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from rich.console import Console

from midas_cli.clock import HostClock
from midas_cli.console import dashboard
from midas_cli.record.lsl_out import LiveOutlets
from midas_cli.record.stats import DeviceRecord
from midas_cli.record.status import DeviceStatus, RecorderSnapshot
from midas_cli.session.reader import Session
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
from midas_cli.session.writer import SessionMetadata, SessionWriter
from helpers.cli import midas, record_until
from helpers.lsl_fixture import loopback_lsl_config

pytest.importorskip("pylsl", reason="pylsl (pip install pylsl==1.18.6) is not installed")

ARM = StreamSpec("arm", "arm", (SEQ, T_HOST, Column("x_mm", "float", "mm", 3, description="position"),
                                Column("angle_deg", "float", "deg", 3)), 100.0)
CLICKS = StreamSpec("clicks", "buttons", (SEQ, T_HOST, Column("button", "int", "id")), None)
SPACING_TOLERANCE_S = 0.002


@pytest.fixture(scope="module", autouse=True)
def loopback_only(tmp_path_factory: pytest.TempPathFactory) -> None:
    loopback_lsl_config(tmp_path_factory.mktemp("lsl"))


def _source_session(root: Path) -> Path:
    """A finished session: `arm` at ~100 Hz with jittered spacing (1.2 s) and an event stream `clicks`
    (8 irregular button presses); every value is unique within its stream."""
    rng = np.random.default_rng(7)
    clock = HostClock.anchored_now()
    writer = SessionWriter.create(root, SessionMetadata("7", "replay", 1), clock,
                                  {"arm": {"kind": "kinematics"}, "buttons": {"kind": "buttons"}}, [ARM, CLICKS])
    t0 = clock.now_ns()
    arm_t = t0 + np.cumsum(rng.integers(7_000_000, 13_000_000, 120))
    writer.append("arm", ARM.format_rows([(i, int(t), 100 + i * 0.25, math.sin(i) * 90)
                                          for i, t in enumerate(arm_t)]))
    click_t = np.sort(rng.integers(arm_t[0], arm_t[-1], 8))
    writer.append("clicks", CLICKS.format_rows([(i, int(t), 10 + 3 * i) for i, t in enumerate(click_t)]))
    writer.finalize("complete", "test", int(arm_t[-1]) + 1_000_000, {})
    return writer.folder


def _replay(*args: str) -> subprocess.Popen:
    env = {**os.environ, "NO_COLOR": "1", "COLUMNS": "200"}
    return subprocess.Popen([sys.executable, "-m", "midas_cli", "replay", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


def _stop(process: subprocess.Popen) -> tuple[int, str]:
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=30)
    return process.returncode, stderr


def _check_round_trip(source: Session, recorded: Session, stream: str, channels: list[str]) -> None:
    """The recorded rows are consecutive source rows (wrapping at a --loop pass) with equal values, and
    consecutive LSL timestamps are as far apart as the source's host times (within one pass)."""
    src, got = source.read_stream(stream), recorded.read_stream(stream)
    assert list(got.columns) == ["seq", "t_host_ns", "t_lsl_s", "src_seq", *channels]  # labels came through <desc>
    first = np.flatnonzero(np.isclose(src[channels[0]].to_numpy(float), got[channels[0]].iloc[0], atol=1e-9))
    assert len(first) == 1
    at = (first[0] + np.arange(len(got))) % len(src)
    assert np.allclose(got[channels].to_numpy(float), src[channels].to_numpy(float)[at], atol=1e-9)
    assert np.array_equal(got["src_seq"].to_numpy(float), src["seq"].to_numpy(float)[at])  # the sender's seq kept
    same_pass = np.diff(at) == 1
    src_gap = np.diff(src["t_host_ns"].to_numpy(np.int64)[at]) / 1e9
    got_gap = np.diff(got["t_lsl_s"].to_numpy(float))
    assert same_pass.sum() >= 5
    assert np.abs(got_gap - src_gap)[same_pass].max() < SPACING_TOLERANCE_S


def test_replayed_session_is_recorded_back_with_its_values_and_spacing(tmp_path: Path) -> None:
    import pylsl

    source = Session.open(_source_session(tmp_path / "source"))
    sid = f"midas:{source.path.name}"
    player = _replay(str(source.path), "--to", "lsl", "--loop", "--delay", "0")
    try:
        found = pylsl.resolve_bypred(f"source_id='{sid}:arm'", 1, 30)
        assert found, "the replayed stream was not announced"
        inlet = pylsl.StreamInlet(found[0])
        info = inlet.info(timeout=10)
        channel = info.desc().child("channels").child("channel")
        assert (info.name(), info.type(), info.nominal_srate(), info.channel_count()) == ("arm", "kinematics", 100, 3)
        assert channel.child_value("label") == "seq"  # the device's own counter first: gaps = lost samples
        channel = channel.next_sibling()
        assert (channel.child_value("label"), channel.child_value("unit")) == ("x_mm", "mm")
        inlet.close_stream()
        result = record_until(tmp_path / "out", [
            "--device", f"arm=lsl://?source_id={sid}:arm&timeout=30",
            "--device", f"clicks=lsl://?source_id={sid}:clicks&timeout=30",
            "--subject", "1", "--task", "replayed", "--trial", "1", "--no-tui"], {"arm": 150, "clicks": 10})
    finally:
        code, stderr = _stop(player)
    assert result.returncode == 0, result.stderr
    assert code == 0, stderr
    assert stderr.strip().splitlines()[-1].startswith("midas: replay stopped by Ctrl-C after ")
    recorded = Session.open(result.stdout.strip().splitlines()[-1])
    assert recorded.stream_spec("clicks").is_events  # irregular (nominal_srate 0) -> an event stream
    _check_round_trip(source, recorded, "arm", ["x_mm", "angle_deg"])
    _check_round_trip(source, recorded, "clicks", ["button"])


def test_faster_replay_keeps_the_recorded_spacing_in_its_timestamps(tmp_path: Path) -> None:
    import pylsl

    from midas_cli.interop.lsl_replay import plan_replay, replay

    source = Session.open(_source_session(tmp_path))
    plan = plan_replay(source.path, ["arm"], speed=4.0, loop=True, delay_s=0.0)
    stop = threading.Event()
    player = threading.Thread(target=replay, args=(plan, stop.is_set), daemon=True)
    player.start()
    try:
        found = pylsl.resolve_bypred(f"source_id='midas:{source.path.name}:arm'", 1, 30)
        assert found
        inlet = pylsl.StreamInlet(found[0])
        stamps, samples = [], []
        deadline = time.monotonic() + 60
        while len(stamps) < 200 and time.monotonic() < deadline:
            chunk, times = inlet.pull_chunk(timeout=0.2)
            samples += chunk
            stamps += times
        inlet.close_stream()
    finally:
        stop.set()
        player.join(timeout=10)
    src = source.read_stream("arm")
    x = src["x_mm"].to_numpy(float)
    at = np.array([int(np.flatnonzero(np.isclose(x, s[1], atol=1e-9))[0]) for s in samples])  # s[0] is seq
    same_pass = np.diff(at) == 1
    src_gap = np.diff(src["t_host_ns"].to_numpy(np.int64)[at]) / 1e9
    assert same_pass.sum() >= 100 and not player.is_alive()
    assert np.abs(np.diff(stamps) - src_gap)[same_pass].max() < 1e-6  # recorded spacing, not a quarter of it
    wrapped = np.diff(stamps)[~same_pass]
    assert np.all(wrapped > 0)  # a new --loop pass goes on forward in time


def test_markers_are_replayed_as_a_string_stream(tmp_path: Path) -> None:
    """Every recording has an `events` stream (the operator's markers, text): replaying a session that holds
    markers was an internal error ('could not convert string to float'); LSL's own marker streams are strings."""
    import pylsl

    from midas_cli.interop.lsl_replay import plan_replay, replay
    from midas_cli.record.markers import events_spec

    clock = HostClock.anchored_now()
    events = events_spec()
    writer = SessionWriter.create(tmp_path, SessionMetadata("7", "replay", 1), clock,
                                  {"arm": {"kind": "kinematics"}, "operator": {"kind": "operator"}}, [ARM, events])
    t0 = clock.now_ns()
    writer.append("arm", ARM.format_rows([(i, t0 + i * 10_000_000, i * 0.5, 0.0) for i in range(100)]))
    writer.append("events", events.format_rows([(0, t0 + 200_000_000, 'needle "in", 1', "key"),
                                                (1, t0 + 700_000_000, "knot", "mark")]))
    writer.finalize("complete", "test", t0 + 1_000_000_000, {})
    plan = plan_replay(writer.folder, loop=True, delay_s=0.0)
    stop = threading.Event()
    player = threading.Thread(target=replay, args=(plan, stop.is_set), daemon=True)
    player.start()
    try:
        found = pylsl.resolve_bypred(f"source_id='midas:{writer.folder.name}:events'", 1, 30)
        assert found, "the markers were not announced"
        inlet = pylsl.StreamInlet(found[0])
        info = inlet.info(timeout=10)
        # LSL's marker convention: type Markers, ONE string channel (marker-aware readers skip wider ones)
        assert info.channel_format() == pylsl.cf_string and info.channel_count() == 1
        assert info.type() == "Markers" and info.desc().child("midas").child_value("not_sent") == "seq,source"
        markers, deadline = [], time.monotonic() + 30
        while len(markers) < 3 and time.monotonic() < deadline:
            sample, _ = inlet.pull_sample(timeout=0.5)
            if sample is not None:
                markers.append(sample)
        inlet.close_stream()
    finally:
        stop.set()
        player.join(timeout=10)
    assert len(markers) >= 3 and {tuple(m) for m in markers} <= {('needle "in", 1',), ("knot",)}


def test_record_lsl_out_publishes_the_rows_it_writes(tmp_path: Path) -> None:
    """Each stream's rows as written (the worker's outlets), and the operator's markers live (the
    recorder's outlet: a Markers stream whose one channel is the text)."""
    import pylsl

    received: list[tuple[float, list[float]]] = []
    state: dict = {"markers": []}
    sock = tmp_path / "control.sock"

    def enough_received(out: Path) -> bool:
        if "inlet" not in state:
            sessions = list(out.glob("*/manifest.json"))
            found = sessions and pylsl.resolve_bypred(f"source_id='midas:{sessions[0].parent.name}:emht'", 1, 1)
            if not found:
                return False
            state["inlet"] = pylsl.StreamInlet(found[0])
            state["info"] = state["inlet"].info(timeout=10)
            assert midas("ctl", "--control", str(sock), "mark", "first bite").returncode == 0
            markers = pylsl.resolve_bypred(f"source_id='midas:{sessions[0].parent.name}:events'", 1, 30)
            state["markers_inlet"] = pylsl.StreamInlet(markers[0])
            state["markers_info"] = state["markers_inlet"].info(timeout=10)
            state["markers_inlet"].open_stream(timeout=10)  # connected: what is marked now reaches it
            assert midas("ctl", "--control", str(sock), "mark", "knot, tied").returncode == 0
        samples, stamps = state["inlet"].pull_chunk(timeout=0.2)
        received.extend(zip(stamps, samples))
        marker, _ = state["markers_inlet"].pull_sample(timeout=0.0)
        state["markers"] += [marker] if marker else []
        if len(received) < 100 or not state["markers"]:
            return False
        state["inlet"].close_stream()  # before the recording stops: no broken-off stream to report
        state["markers_inlet"].close_stream()
        return True

    result = record_until(tmp_path / "out", ["--simulate", "--lsl-out", "--subject", "1", "--task", "lslout",
                                             "--trial", "1", "--no-tui", "--control", str(sock)],
                          until=enough_received, timeout=120)
    assert result.returncode == 0, result.stderr
    assert len(received) >= 100
    session = Session.open(result.stdout.strip().splitlines()[-1])
    assert session.manifest["lsl_out"] == {"enabled": True, "lsl_config": os.environ["LSLAPICFG"]}
    assert (f"midas: --lsl-out: LSL outlets accept connections on every network interface (liblsl "
            f"configuration {os.environ['LSLAPICFG']})") in result.stderr
    spec = session.stream_spec("emht")
    info = state["info"]
    labels, units, channel = [], [], info.desc().child("channels").child("channel")
    while not channel.empty():
        labels.append(channel.child_value("label"))
        units.append(channel.child_value("unit"))
        channel = channel.next_sibling()
    channels = [c for c in spec.columns if c.name != "t_host_ns"]  # seq first, then the data columns
    assert labels == [c.name for c in channels] and units == [c.unit for c in channels]
    assert (info.name(), info.type(), info.nominal_srate()) == ("emht", "MoCap", 240)
    assert ["knot, tied"] in state["markers"]  # sent after the consumer connected, as written
    assert all(m in (["first bite"], ["knot, tied"]) for m in state["markers"])
    assert state["markers_info"].type() == "Markers" and state["markers_info"].channel_count() == 1
    frame = session.read_stream("emht")
    times = frame["t_host_ns"].to_numpy(np.int64)
    stamps_ns = np.array([s for s, _ in received]) * 1e9 + session.manifest["clock"]["anchor_ns"]
    rows = np.clip(np.searchsorted(times, stamps_ns.round().astype(np.int64) - 1_000), 0, len(times) - 1)
    assert np.abs(times[rows] - stamps_ns).max() < 1_000  # each timestamp is a row's host time
    values = frame[[c.name for c in channels]].to_numpy(float)[rows]
    assert np.array_equal(values, np.array([v for _, v in received]), equal_nan=True)


def test_a_failing_outlet_is_a_warning_and_recording_goes_on(monkeypatch: pytest.MonkeyPatch) -> None:
    import midas_cli.record.lsl_out as lsl_out

    def broken(*_args):
        raise RuntimeError("no network")

    monkeypatch.setattr(lsl_out, "open_outlet", broken)
    warnings: list[str] = []
    outlets = LiveOutlets("s", "test", 0, warnings.append)
    outlets.publish(ARM, [(0, 1, 1.0, 2.0)])
    outlets.publish(ARM, [(1, 2, 1.0, 2.0)])  # off for this stream: not retried, not reported again
    assert warnings == ["--lsl-out: stream arm is no longer published (RuntimeError: no network); "
                        "recording goes on"]
    record = DeviceRecord("arm", "test", "sim://", {}, ["arm"])
    record.events.append({"t_host_ns": 0, "event": "warning", "message": warnings[0]})
    assert record.warning == warnings[0]
    screen = Console(width=200, record=True, file=open(os.devnull, "w"))
    screen.print(dashboard(RecorderSnapshot("/s", "s", 1.0, None, 10**9, 0.0, 0, (
        DeviceStatus("arm", "test", "sim://", "ok", 0, "", (), {}, record.warning),))))
    assert f"arm: {warnings[0]}" in screen.export_text()  # on the live screen although the device is ok


@pytest.mark.parametrize(("args", "code", "message"), [
    (["--streams", "arm,nope"], 2, "--streams: nope not in "),
    (["--speed", "0"], 2, "--speed must be a finite number > 0"),
    (["--to", "ros2"], 2, "--to ros2: expected one of lsl"),
], ids=["unknown stream", "speed 0", "unknown target"])
def test_bad_replay_input_is_one_line_and_an_exit_code(tmp_path: Path, args: list[str], code: int,
                                                        message: str) -> None:
    result = midas("replay", str(_source_session(tmp_path)), *args)
    assert result.returncode == code
    assert result.stderr.count("\n") == 1 and message in result.stderr


def test_replay_of_no_session_is_a_session_error(tmp_path: Path) -> None:
    result = midas("replay", str(tmp_path / "nowhere"))
    assert result.returncode == 4
    assert result.stderr.count("\n") == 1 and "is not a folder" in result.stderr


def test_a_host_time_far_outside_the_session_ends_the_replay_instead_of_a_wait_for_ever(tmp_path: Path) -> None:
    """Only the file was edited (the manifest still gives the old last time): the sample itself is
    refused when its turn comes, with one line, where replay used to wait 3 years for it."""
    session = _source_session(tmp_path)
    path = session / "streams" / "arm.csv"
    lines = path.read_bytes().splitlines(keepends=True)
    fields = lines[-1].split(b",")
    fields[1] = str(int(fields[1]) + 10**17).encode()
    path.write_bytes(b"".join(lines[:-1]) + b",".join(fields))
    result = midas("replay", str(session), "--delay", "0", "--speed", "20", timeout=60)
    assert result.returncode == 4, result.stderr
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("midas: error: ") and "streams/arm.csv holds t_host_ns" in last and "far outside" in last
