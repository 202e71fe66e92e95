"""Recorder internals that an end-to-end run rarely exercises: overflow accounting, health, rendering."""

from __future__ import annotations

import io
import queue

import numpy as np
from rich.console import Console

from midas_cli.clock import HostClock
from midas_cli.console import dashboard, status_line
from midas_cli.devices.registry import describe_device
from midas_cli.record.messages import DataBatch
from midas_cli.record.recorder import _health
from midas_cli.record.stats import DeviceRecord, StreamStats
from midas_cli.record.status import DeviceStatus, RecorderSnapshot, StreamStatus
from midas_cli.record.worker import _flush

SPEC = describe_device("video", "sim://video?rate=30").streams[0]


def _batch(seqs, dropped: int = 0) -> DataBatch:
    seq = np.asarray(seqs, dtype=np.int64)
    t = 1_000_000_000 + seq * 33_333_333
    return DataBatch("video", "video", "", seq, t, (int(seq[-1]), int(t[-1]), 0.0), dropped, 0)


def test_a_full_queue_drops_counted_rows_not_silently() -> None:
    device = describe_device("video", "sim://video?rate=30")
    full: queue.Queue = queue.Queue(maxsize=1)
    full.put("occupied")
    totals = {"dropped": 0, "corrupt": 0}
    pending = {"video": [(i, 1000 + i, i / 30) for i in range(7)]}
    _flush(device, {"video": SPEC}, pending, full, totals)
    assert totals["dropped"] == 7 and pending["video"] == []


def test_sequence_gaps_are_attributed_to_overflow_outage_or_nothing() -> None:
    stats = StreamStats(SPEC)
    stats.add(_batch(range(0, 10)), committed_ns=2_000_000_000)
    stats.add(_batch(range(15, 20), dropped=5), committed_ns=2_000_000_000)  # 5 dropped by the queue
    assert stats.missing_unexplained == 0
    stats.reopened = True
    stats.add(_batch(range(40, 45), dropped=5), committed_ns=2_000_000_000)  # outage across a reconnect
    assert stats.missing_outage == 20 and stats.missing_unexplained == 0
    stats.add(_batch([45, 46, 48], dropped=5), committed_ns=2_000_000_000)  # the device skipped one: unexplained
    assert stats.missing_unexplained == 1
    extra = stats.manifest_extra()
    assert extra["missing_explained"] == {"outage": 20, "queue_overflow": 5}
    assert extra["latency_ms"]["n"] == 23


def test_latency_percentiles_come_from_the_histogram() -> None:
    stats = StreamStats(SPEC)
    batch = _batch(range(100))
    committed = int(batch.t_host_ns[-1]) + 2_000_000  # 2 ms after the last sample
    stats.add(batch, committed)
    latency = stats.latency_ms()
    assert latency["max"] == round((committed - batch.t_host_ns[0]) / 1e6, 3)
    assert 2.0 <= latency["p50"] <= latency["p99"] <= latency["max"] + 0.05


def _stream(age: float | None, rate: float | None) -> StreamStatus:
    return StreamStatus("emht", 240.0, rate, 100, age, 0, 0, 0, {"s1_x_mm": 1.0, "s1_y_mm": 2.0, "s1_z_mm": 3.0})


def test_health_states() -> None:
    record = DeviceRecord("emht", "emht", "sim://emht", {}, ["emht"], state="ok")
    assert _health(record, (_stream(0.01, 240.0),)) == "ok"
    assert _health(record, (_stream(0.9, 240.0),)) == "degraded"
    assert _health(record, (_stream(0.01, 150.0),)) == "degraded"
    record.state = "lost"
    assert _health(record, (_stream(0.01, 240.0),)) == "lost"


def test_renderers_show_rates_and_positions() -> None:
    device = DeviceStatus("emht", "emht", "sim://emht", "ok", 2, "", (_stream(0.01, 239.5),))
    snapshot = RecorderSnapshot("/s", "t_S1_T1_x", 75.0, 600.0, 10 * 2**30, 70_000.0, 123, (device,))
    line = status_line(snapshot)
    assert line.startswith("[00:01:15]") and "emht ok 239.5/240Hz n=100" in line and "reconnects=2" in line
    console = Console(file=io.StringIO(), width=80, color_system=None)
    console.print(dashboard(snapshot))
    screen = console.file.getvalue()
    assert "239.5 / 240" in screen and "00:10:00" in screen and "10.0 GB" in screen
    assert max(len(line) for line in screen.splitlines()) <= 80


def test_host_clocks_with_one_anchor_agree_across_instances() -> None:
    clock = HostClock.anchored_now()
    other = HostClock(clock.anchor_ns)
    a, b, c = clock.now_ns(), other.now_ns(), clock.now_ns()
    assert a <= b <= c


def test_a_worker_bug_is_reported_with_its_traceback(monkeypatch) -> None:
    import threading

    import pytest

    from midas_cli.record import worker

    def broken(*_args, **_kwargs):
        raise RuntimeError("bug in a backend")

    monkeypatch.setattr(worker, "create_device", broken)
    out: queue.Queue = queue.Queue()
    job = worker.WorkerJob("emht", "sim://emht", 0, 0, 0, 1.0, parent_pid=__import__("os").getppid())
    with pytest.raises(SystemExit) as exit_info:
        worker.run_worker(job, out, threading.Event())
    assert exit_info.value.code == 1
    events = [out.get_nowait() for _ in range(out.qsize())]
    assert [e.event for e in events] == ["crashed", "exited"]
    assert "RuntimeError: bug in a backend" in events[0].message and "Traceback" in events[0].message
