"""Recorder internals that an end-to-end run rarely exercises: the worker's write-then-account path,
queue overflow, write failures, latency windows, health, rendering."""

from __future__ import annotations

import errno
import io
import os
import queue
import threading

import numpy as np
import pytest
from rich.console import Console

from midas_cli.clock import HostClock
from midas_cli.console import dashboard, status_line
from midas_cli.devices.registry import describe_device
from midas_cli.record import worker
from midas_cli.record.messages import DataBatch, DeviceEvent
from midas_cli.record.recorder import Recorder, RecordPlan
from midas_cli.record.stats import device_health as _health
from midas_cli.record.stats import DeviceRecord, StreamStats
from midas_cli.record.status import DeviceStatus, RecorderSnapshot, StreamStatus
from midas_cli.record.worker import StreamWriteFailed, WorkerOutput, _flush
from midas_cli.session.writer import SessionMetadata

VIDEO = describe_device("video", "sim://video?rate=30")
SPEC = VIDEO.streams[0]


def _batch(seqs, committed_ns: int = 2_000_000_000) -> DataBatch:
    seq = np.asarray(seqs, dtype=np.int64)
    t = 1_000_000_000 + seq * 33_333_333
    return DataBatch("video", "video", seq, t, np.full(len(seq), committed_ns, dtype=np.int64),
                     (int(seq[-1]), int(t[-1]), 0.0), 10 * len(seq), 1000, 0)


def _rows(seqs) -> list[tuple]:
    return [(i, 1_000_000_000 + i * 33_333_333, i / 30) for i in seqs]


def _output(tmp_path, out, every_s: float = 0.0) -> tuple[WorkerOutput, object]:
    """A worker's output on a stream file that holds only its header, as the recorder leaves it (by
    default telling the recorder after every write; the recorder's own interval is BOOKKEEPING_EVERY_S)."""
    path = tmp_path / "video.csv"
    path.write_text(SPEC.header_line())
    output = WorkerOutput("video", out, HostClock.anchored_now(), every_s)
    output.open({"video": str(path)})
    return output, path


class _PeekingQueue:
    """Records, at each put, what the stream file held at that moment."""

    def __init__(self, path) -> None:
        self.path, self.seen = path, []

    def put_nowait(self, batch: DataBatch) -> None:
        self.seen.append((batch, self.path.read_text()))


def test_the_worker_writes_rows_before_it_tells_the_recorder(tmp_path) -> None:
    output, path = _output(tmp_path, None)
    output.out = peeking = _PeekingQueue(path)
    _flush(VIDEO, {"video": SPEC}, {"video": _rows(range(3))}, output)
    _flush(VIDEO, {"video": SPEC}, {"video": _rows(range(3, 5))}, output)
    (first, on_disk_1), (second, on_disk_2) = peeking.seen
    assert on_disk_1 == SPEC.header_line() + SPEC.format_rows(_rows(range(3)))
    assert on_disk_2 == SPEC.header_line() + SPEC.format_rows(_rows(range(5)))
    assert list(second.seq) == [3, 4] and first.nbytes == len(SPEC.format_rows(_rows(range(3))))
    assert (first.committed_ns > first.t_host_ns).all() and second.committed_ns[0] >= first.committed_ns[0]


def test_bookkeeping_of_quick_reads_goes_in_one_message_and_before_any_event(tmp_path) -> None:
    out: queue.Queue = queue.Queue()
    output, path = _output(tmp_path, out, every_s=3600)
    output.last_sent_ns = output.clock.now_ns()  # the interval has just begun
    for k in range(5):
        _flush(VIDEO, {"video": SPEC}, {"video": _rows(range(2 * k, 2 * k + 2))}, output)
    assert out.empty(), "reads within the interval are gathered, not sent one by one"
    assert path.read_text() == SPEC.header_line() + SPEC.format_rows(_rows(range(10))), "but on disk at once"
    output.event("lost", "gone")
    batch, event = out.get_nowait(), out.get_nowait()
    assert isinstance(batch, DataBatch) and isinstance(event, DeviceEvent)
    assert list(batch.seq) == list(range(10)) and len(batch.committed_ns) == 10
    assert batch.nbytes == path.stat().st_size - len(SPEC.header_line())
    output.every_ns = 0
    _flush(VIDEO, {"video": SPEC}, {"video": _rows(range(10, 11))}, output)
    assert list(out.get_nowait().seq) == [10], "once the interval has passed, the next write sends"


def test_a_full_queue_merges_bookkeeping_instead_of_dropping(tmp_path) -> None:
    out: queue.Queue = queue.Queue(maxsize=2)
    output, path = _output(tmp_path, out)
    out.put("occupied")
    out.put("occupied")
    _flush(VIDEO, {"video": SPEC}, {"video": _rows(range(7))}, output)
    _flush(VIDEO, {"video": SPEC}, {"video": _rows(range(7, 10))}, output)
    assert path.read_text().count("\n") == 1 + 10, "rows are on disk whatever the queue"
    out.get_nowait()
    _flush(VIDEO, {"video": SPEC}, {"video": _rows(range(10, 12))}, output)
    merged = out.queue[-1]
    assert list(merged.seq) == list(range(12)) and len(merged.committed_ns) == 12 and output.held == {}
    assert merged.nbytes == path.stat().st_size - len(SPEC.header_line())
    stats = StreamStats(SPEC)
    stats.add(merged, merged.committed_ns)
    assert stats.samples == 12 and stats.missing_unexplained == 0 and stats.latency_ms()["n"] == 12


def test_held_bookkeeping_reaches_the_recorder_before_the_next_event(tmp_path) -> None:
    out: queue.Queue = queue.Queue(maxsize=1)
    output, _ = _output(tmp_path, out)
    out.put("occupied")
    _flush(VIDEO, {"video": SPEC}, {"video": _rows(range(4))}, output)
    out.get_nowait()
    threading.Timer(0.2, out.get).start()  # the recorder takes the held batch; the event then fits
    output.event("lost", "gone")
    assert isinstance(out.get(timeout=2), DeviceEvent) and output.held == {}


def test_a_missing_stream_file_is_an_error_not_a_new_file(tmp_path) -> None:
    output = WorkerOutput("video", queue.Queue(), HostClock.anchored_now())
    with pytest.raises(StreamWriteFailed, match="No such file"):
        output.open({"video": str(tmp_path / "streams" / "video.csv")})
    assert not (tmp_path / "streams").exists()


def test_a_failed_write_becomes_an_event_that_stops_the_recording(tmp_path, monkeypatch) -> None:
    path = tmp_path / "emht.csv"
    path.write_text("header\n")

    def disk_full(self, text: str) -> int:
        raise OSError(errno.EFBIG, "File too large")

    monkeypatch.setattr(worker.StreamAppender, "append", disk_full)
    out: queue.Queue = queue.Queue()
    job = worker.WorkerJob("emht", "sim://emht", 0, 0, 0, 1.0, parent_pid=os.getppid(),
                           stream_files={"emht": str(path)})
    worker.run_worker(job, out, threading.Event())
    events = [out.get_nowait() for _ in range(out.qsize())]
    assert [e.event for e in events] == ["opening", "opened", "write_failed", "exited"]
    failed = events[2]
    assert failed.info["stream"] == "emht" and failed.info["rows"] >= 1 and "File too large" in failed.message
    recorder = Recorder(RecordPlan(SessionMetadata("1", "t", 1), {"emht": "sim://emht"}, tmp_path))
    for event in events:
        recorder._on_event(event)
    assert recorder.fatal_error.startswith("writing the session failed") and "File too large" in recorder.fatal_error
    assert recorder._stop_workers.is_set() and recorder.streams["emht"].dropped == failed.info["rows"]
    assert path.read_text() == "header\n"


def test_sequence_gaps_are_attributed_to_an_outage_or_nothing() -> None:
    stats = StreamStats(SPEC)
    stats.add(_batch(range(0, 10)), committed_ns=2_000_000_000)
    stats.reopened = True
    stats.add(_batch(range(30, 35)), committed_ns=2_000_000_000)  # outage across a reconnect
    assert stats.missing_outage == 20 and stats.missing_unexplained == 0
    stats.add(_batch([35, 36, 38]), committed_ns=2_000_000_000)  # the device skipped one: unexplained
    assert stats.missing_unexplained == 1
    extra = stats.manifest_extra()
    assert extra["missing_explained"] == {"outage": 20} and extra["dropped"] == 0
    assert extra["latency_ms"]["n"] == 18


def test_latency_percentiles_come_from_the_histogram() -> None:
    stats = StreamStats(SPEC)
    batch = _batch(range(100))
    committed = int(batch.t_host_ns[-1]) + 2_000_000  # 2 ms after the last sample
    stats.add(batch, committed)
    latency = stats.latency_ms()
    assert latency["max"] == round((committed - batch.t_host_ns[0]) / 1e6, 3)
    assert 2.0 <= latency["p50"] <= latency["p99"] <= latency["max"] + 0.05


def test_the_latency_window_forgets_what_is_older_than_ten_seconds() -> None:
    stats = StreamStats(SPEC)
    for k in range(31):  # a row every 0.5 s over 15 s; the first took 900 ms to reach disk, the others 3 ms
        t_host = k * 500_000_000
        delay = 900_000_000 if k == 0 else 3_000_000
        stats.add(DataBatch("video", "video", np.array([k]), np.array([t_host]), np.array([t_host + delay]),
                            (k, t_host, 0.0), 10, 1000, 0), t_host + delay)
    now = 15_200_000_000
    window = stats.latency_window_ms(now)
    assert window["max"] == window["p99"] == 3.0 and window["n"] == 19, window  # seconds 6..15: k = 12..30
    assert stats.latency_ms()["max"] == 900.0
    assert stats.latency_window_ms(now + 60_000_000_000)["n"] == 0
    status = Recorder._stream_status(stats, now)
    assert status.latency_window_ms == window and set(status.latency_ms) == {"p50", "p99", "max"}


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
    def broken(*_args, **_kwargs):
        raise RuntimeError("bug in a backend")

    monkeypatch.setattr(worker, "create_device", broken)
    out: queue.Queue = queue.Queue()
    job = worker.WorkerJob("emht", "sim://emht", 0, 0, 0, 1.0, parent_pid=os.getppid())
    with pytest.raises(SystemExit) as exit_info:
        worker.run_worker(job, out, threading.Event())
    assert exit_info.value.code == 1
    events = [out.get_nowait() for _ in range(out.qsize())]
    assert [e.event for e in events] == ["opening", "crashed", "exited"]
    assert "RuntimeError: bug in a backend" in events[1].message and "Traceback" in events[1].message
