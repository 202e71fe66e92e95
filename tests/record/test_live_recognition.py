"""`record --live-model` plumbing, in-process: the device workers' feed (bounded, never waits, every row
accounted for), the rig check, the recognition loop's rows and counts, and what the operator sees.

The model is a stand-in with LiveFeed's interface (add / ready / drop_until): these tests are about the
recording's side of the seam; the real model end to end is in test_live_model_record.py."""

from __future__ import annotations

import io
import multiprocessing as mp
import os
import queue
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from midas_cli.clock import HostClock
from midas_cli.console import dashboard, gesture_line, status_line
from midas_cli.devices.lsl.outlet import channel_columns
from midas_cli.devices.rigconfig import parse_rig
from midas_cli.errors import ConfigError
from midas_cli.record.feed import RowFeed
from midas_cli.record.live_model import GestureTracker, LivePlan, check_rig_streams, gestures_spec
from midas_cli.record.messages import DataBatch
from midas_cli.record.recognition import Recognition, RecognitionJob
from midas_cli.record.status import DeviceStatus, GestureStatus, RecorderSnapshot, StreamStatus
from midas_cli.record.worker import WorkerOutput
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
from midas_cli.session.writer import StreamAppender

EMHT = StreamSpec("emht", "emht", (SEQ, T_HOST, Column("s1_x_mm", "float", "mm", 2), Column("s1_y_mm", "float", "mm", 2),
                                   Column("s2_x_mm", "float", "mm", 2)), 240.0)
PLAN = LivePlan("/runs/r1", "r1", "ab" * 32, "mstcn", 10.0, {"emht": ("s2_x_mm", "s1_y_mm")}, ("G1", "G2"))


def _rows(first: int, n: int) -> list[tuple]:
    return [(i, 1_000_000 * i, float(i), None if i % 7 == 0 else -float(i), 2.0 * i) for i in range(first, first + n)]


# -- the feed: bounded, never waits, conserves rows -------------------------------------------------
def _drain(receiver) -> tuple[list[tuple], int]:
    """Every message until the feed closed its end: the batches, and the last running drop count."""
    batches, dropped = [], 0
    while True:
        try:
            message = receiver.recv()
        except EOFError:
            return batches, dropped
        batches += message[0]
        dropped = message[1]


def test_the_feed_sends_the_needed_columns_in_the_models_order_and_ignores_other_streams() -> None:
    receiver, sender = mp.Pipe(duplex=False)
    feed = RowFeed(sender, dict(PLAN.streams), every_s=0.0)
    other = StreamSpec("fps", "fps", (SEQ, T_HOST, Column("ch1_adc", "int")), 250.0)
    feed.offer(EMHT, _rows(0, 5))
    feed.offer(other, [(0, 5, 1)])
    feed.offer(EMHT, _rows(5, 3))
    feed.close()
    batches, dropped = _drain(receiver)
    assert dropped == 0 and {stream for stream, _, _ in batches} == {"emht"}
    times = np.concatenate([t for _, t, _ in batches])
    values = np.concatenate([v for _, _, v in batches])
    assert times.tolist() == [1_000_000 * i for i in range(8)]
    assert values[:, 0].tolist() == [2.0 * i for i in range(8)]  # s2_x_mm first, as the model reads them
    assert np.isnan(values[0, 1]) and np.isnan(values[7, 1]) and values[1, 1] == -1.0  # a missing value: NaN


def test_a_feed_nobody_reads_drops_rows_counted_and_never_blocks_the_worker() -> None:
    receiver, sender = mp.Pipe(duplex=False)
    feed = RowFeed(sender, dict(PLAN.streams), max_rows=4, every_s=0.0)
    offered = 0
    for k in range(400):  # ~8 MB of rows: far more than the pipe and the queue hold
        feed.offer(EMHT, _rows(k * 1000, 1000))
        offered += 1000
    assert feed.dropped > 0  # the offers came back while nobody read: their rows were counted, not waited for
    drained: list = []
    reader = threading.Thread(target=lambda: drained.append(_drain(receiver)))
    reader.start()
    feed.close(timeout_s=30)
    reader.join(timeout=60)
    batches, dropped = drained[0]
    received = sum(len(t) for _, t, _ in batches)
    assert dropped == feed.dropped and received + dropped == offered  # every row sent or counted


def test_rows_offered_after_the_recognition_is_gone_are_counted() -> None:
    receiver, sender = mp.Pipe(duplex=False)
    receiver.close()
    feed = RowFeed(sender, dict(PLAN.streams), every_s=0.0)
    feed.offer(EMHT, _rows(0, 10))
    feed._thread.join(timeout=10)  # its send failed: the feeder has ended
    feed.offer(EMHT, _rows(10, 10))
    assert feed.dropped == 10
    feed.close()


# -- the rig check ---------------------------------------------------------------------------------
def test_a_model_needing_streams_or_columns_the_rig_lacks_is_refused_naming_them() -> None:
    plan = LivePlan("/runs/r1", "r1", "0" * 64, "mstcn", 10.0, {"emht": ("s1_x_mm", "s9_x_mm"), "mtm": ("left_x_mm",)},
                    ("G1",))
    with pytest.raises(ConfigError) as error:
        check_rig_streams(plan, {"emht": EMHT}, {"emht": "sim://emht"})
    assert "stream mtm" in str(error.value) and "emht columns s9_x_mm" in str(error.value)
    assert "s1_x_mm" not in str(error.value) and "\n" not in str(error.value)
    checked = check_rig_streams(PLAN, {"emht": EMHT}, {"emht": "sim://emht"})  # all there: no error
    assert checked.nominal_rates_hz == {"emht": 240.0}  # how old a sample may be, as align's
    with pytest.raises(ConfigError, match="rename"):
        check_rig_streams(PLAN, {"emht": EMHT}, {"emht": "sim://emht", "recognition": "sim://emht"})


# -- the recognition loop --------------------------------------------------------------------------
@dataclass(frozen=True)
class _Prediction:
    seq: int
    t_host_ns: int
    class_index: int
    label: str
    probability: float
    decoded: str = "G9"
    decoded_probability: float = 0.25
    t_pred_ns: int = 5


class _Model:
    """LiveFeed's interface: one frame per 100 ms of emht time once a row past it is known; frames
    before ``skip_before_ns`` are skipped when drop_until reaches them."""

    def __init__(self, skip_before_ns: int) -> None:
        self.known_ns = -1
        self.next_seq = 0
        self.skip_before_ns = skip_before_ns
        self.added: list[np.ndarray] = []

    def add(self, stream: str, t_host_ns: np.ndarray, values: np.ndarray) -> None:
        assert stream == "emht" and values.shape == (len(t_host_ns), 2)
        self.added.append(values)
        self.known_ns = int(t_host_ns[-1])

    def drop_until(self, t_host_ns: int) -> int:
        skipped = 0
        while self.next_seq * 100_000_000 < min(self.skip_before_ns, self.known_ns):
            self.next_seq += 1
            skipped += 1
        return skipped

    def ready(self) -> list[_Prediction]:
        out = []
        while self.next_seq * 100_000_000 < self.known_ns:
            k = self.next_seq
            out.append(_Prediction(k, k * 100_000_000, k % 2, f"G{k % 2 + 1}", 0.5 + k / 1000))
            self.next_seq += 1
        return out

    def flush(self) -> list[_Prediction]:
        """The end of the input: a delayed model's held-back frame (one here), then nothing."""
        if self.flushed:
            return []
        k, self.next_seq, self.flushed = self.next_seq, self.next_seq + 1, True
        return [_Prediction(k, k * 100_000_000, 0, "G1", 0.6)]

    flushed = False


def test_the_recognition_writes_a_row_per_frame_and_counts_what_it_skipped(tmp_path: Path) -> None:
    spec = gestures_spec(PLAN)
    # as a marker stream (--lsl-out, replay, XDF) its one string channel is what the screen shows
    assert [c.name for c in channel_columns(spec)] == ["decoded"]
    assert StreamSpec.from_manifest(spec.name, spec.to_manifest()) == spec
    path = tmp_path / "gestures_live.csv"
    StreamAppender(path, create=True).append(spec.header_line())
    out: queue.Queue = queue.Queue()
    output = WorkerOutput("recognition", out, HostClock.anchored_now(), every_s=0.0)
    output.open({spec.name: str(path)})
    feed, sender = mp.Pipe(duplex=False)  # one worker's feed: two messages, read one per pass of the loop
    for dropped, rows in ((3, _rows(0, 250)), (5, _rows(250, 400))):
        sender.send(([("emht", np.array([r[1] for r in rows]), np.array([[r[4], r[2]] for r in rows]))], dropped))
    sender.close()
    idle, sender = mp.Pipe(duplex=False)  # another worker's, closed without a row
    sender.close()
    job = RecognitionJob(PLAN, output.clock.anchor_ns, os.getpid(), str(path), "session")
    model = _Model(skip_before_ns=450_000_000)  # frames 3 and 4 are skipped once it has predicted
    counts = Recognition(job, output).run(model, [feed, idle])
    output.close()
    assert counts == {"frames_skipped": 2, "input_rows_dropped": 5}
    lines = path.read_text().splitlines()
    assert lines[0] == "seq,t_host_ns,t_pred_ns,class,probability,decoded,decoded_probability,t_decoded_ns"
    rows = [line.split(",") for line in lines[1:]]
    # what came before the first prediction is predicted (frames 0-2 of 249 ms of rows), never skipped; once
    # every feed has closed, the frame the model still held back (flush) is written last
    assert [int(r[0]) for r in rows] == [0, 1, 2, 5, 6, 7] and [int(r[1]) for r in rows][-1] == 700_000_000
    assert all(int(r[2]) == 5 for r in rows) and rows[1][3] == '"G2"'  # the model's own t_pred_ns
    assert all(r[5:7] == ['"G9"', "0.2500"] and int(r[7]) >= output.clock.anchor_ns for r in rows)
    batches = [m for m in _all(out) if isinstance(m, DataBatch)]
    assert batches and batches[-1].last_row[:4:3] == (7, "G1") and batches[-1].stream == "gestures_live"


def _all(out: queue.Queue) -> list:
    return [out.get_nowait() for _ in range(out.qsize())]


# -- what the operator sees ----------------------------------------------------------------------
def test_the_tracker_reports_the_current_gesture_since_its_first_frame_and_the_latency() -> None:
    tracker = GestureTracker(10.0)
    assert tracker.status(0) is None
    # rows: seq, t_host, t_pred, class, probability, decoded, decoded_probability, t_decoded: the decoded
    # class is what the operator sees, with the latency of its decision
    tracker.update((0, 1_000_000_000, 1_002_000_000, "G4", 0.5, "G1", 0.9, 1_012_000_000))
    tracker.update((5, 1_500_000_000, 1_502_000_000, "G1", 0.8, "G1", 0.8, 1_520_000_000))
    status = tracker.status(1_600_000_000)
    assert status == GestureStatus("G1", 0.8, 0.6, 20.0, 0.08)
    tracker.update((6, 1_600_000_000, 1_601_000_000, "G1", 0.6, "G3", 0.7, 1_605_000_000))
    assert tracker.status(1_700_000_000) == GestureStatus("G3", 0.7, 0.1, 5.0, 0.095)


def _screen(snapshot: RecorderSnapshot, width: int = 80) -> str:
    console = Console(file=io.StringIO(), width=width, color_system=None)
    console.print(dashboard(snapshot))
    return console.file.getvalue()


def test_the_live_screen_and_status_line_show_the_gesture_on_one_line() -> None:
    emht = StreamStatus("emht", 240.0, 240.0, 100, 0.01, 0, 0, 0, {"s1_x_mm": 1.0, "s1_y_mm": 2.0, "s1_z_mm": 3.0})
    live = StreamStatus("gestures_live", 10.0, 10.0, 50, 0.05, 0, 0, 0, {"class": "G3", "probability": 0.87})
    devices = (DeviceStatus("emht", "emht", "sim://emht", "ok", 0, "", (emht,)),
               DeviceStatus("recognition", "gestures", "/runs/r1", "ok", 0, "", (live,)))
    gesture = GestureStatus("G3", 0.87, 2.4, 12.0, 0.05)
    snapshot = RecorderSnapshot("/s", "s", 5.0, None, 10**9, 0.0, 0, devices, recognising=True, gesture=gesture)
    screen = _screen(snapshot)
    assert "gesture G3  p 0.87  for 2.4 s  latency 12 ms" in screen and "STALE" not in screen
    assert max(len(line) for line in screen.splitlines()) <= 80
    assert "gesture G3 p=0.87 for 2.4s latency 12ms" in status_line(snapshot)
    waiting = RecorderSnapshot("/s", "s", 5.0, None, 10**9, 0.0, 0, devices, recognising=True)
    assert "gesture: waiting for the first frame" in _screen(waiting)
    assert "gesture" not in _screen(RecorderSnapshot("/s", "s", 5.0, None, 10**9, 0.0, 0, devices[:1]))
    assert "STALE 3.0 s" in gesture_line(GestureStatus("G3", 0.87, 2.4, 12.0, 3.0)).plain


def test_the_rig_files_live_model_is_relative_to_the_rig_file_and_checked_strictly() -> None:
    base = {"rig": {"name": "r", "platform": "davinci-xi"}, "devices": {"fps": {"url": "sim://fps"}}}
    rig = parse_rig({**base, "live": {"model": "runs/r1"}}, "/etc/midas/rig.toml")
    assert rig.live_model == "/etc/midas/runs/r1"
    assert parse_rig(base, "/etc/midas/rig.toml").live_model is None
    with pytest.raises(ConfigError, match="unknown key live.modle"):
        parse_rig({**base, "live": {"modle": "runs/r1"}}, "/etc/midas/rig.toml")


def test_rows_the_feed_cannot_take_are_counted_and_never_raise_into_the_worker() -> None:
    receiver, sender = mp.Pipe(duplex=False)
    feed = RowFeed(sender, {"emht": ("s1_x_mm", "s9_x_mm")}, every_s=0.0)  # a column a reopened device lacks
    feed.offer(EMHT, _rows(0, 4))
    feed.offer(EMHT, [(4, 4_000_000, "not a number", 1.0, 2.0)])
    feed.close()  # the feeder thread takes the columns: what it cannot take is counted there
    assert feed.dropped == 5
    assert _drain(receiver) == ([], 5)
    receiver, sender = mp.Pipe(duplex=False)
    feed = RowFeed(sender, dict(PLAN.streams), every_s=0.5)  # a bad row among good ones, sent together
    feed.offer(EMHT, _rows(1, 3))
    feed.offer(EMHT, [(4, 4_000_000, 4.0, "not a number", 8.0)])
    feed.offer(EMHT, _rows(5, 2))
    feed.close()
    batches, dropped = _drain(receiver)
    assert dropped == 1 and np.concatenate([t for _, t, _ in batches]).tolist() == [1_000_000 * i for i in (1, 2, 3, 5, 6)]
