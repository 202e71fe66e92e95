"""`midas eval live`'s comparisons, in-process: live classes against labels on the video frame clock
(accuracy, edit, per segment detection delay). The offline reference end to end: tests/record/
test_live_model_record.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from midas_cli.analysis.live_eval import agreement, detection_delays_ms, evaluate_live, labels_at
from midas_cli.clock import HostClock
from midas_cli.errors import SessionError
from midas_cli.session.labels import write_frame_labels
from midas_cli.session.reader import Session
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
from midas_cli.session.writer import SessionMetadata, SessionWriter

VIDEO = StreamSpec("video", "video", (SEQ, T_HOST, Column("t_device_s", "float", "s", 6, clock="device")), 30.0)
FRAME_NS = 33_333_333
TRUTH = ["", "", *["G1"] * 30, *["G3"] * 20, "", *["G1"] * 17]  # 70 video frames, segments G1, G3, G1


@pytest.fixture(scope="module")
def labelled(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A session with 70 video frames (seq 100...) labelled TRUTH."""
    clock = HostClock.anchored_now()
    writer = SessionWriter.create(tmp_path_factory.mktemp("live-eval"), SessionMetadata("1", "suturing", 1), clock,
                                  {"video": {"kind": "video"}}, [VIDEO])
    t0 = clock.now_ns()
    writer.append("video", VIDEO.format_rows([(100 + i, t0 + i * FRAME_NS, i / 30) for i in range(len(TRUTH))]))
    writer.finalize("complete", "test", t0 + len(TRUTH) * FRAME_NS, {})
    write_frame_labels(writer.folder, range(100, 100 + len(TRUTH)), TRUTH, {"taxonomy": "jigsaws", "source": "test"})
    return writer.folder


def test_live_frames_take_the_label_of_the_latest_video_frame(labelled: Path) -> None:
    session = Session.open(labelled)
    t0 = int(session.read_stream("video")["t_host_ns"].iloc[0])
    times = np.array([t0 - 1, t0, t0 + 2 * FRAME_NS + 1, t0 + 32 * FRAME_NS - 1, t0 + 32 * FRAME_NS, t0 + 10**12])
    assert labels_at(session, times, "gestures").tolist() == ["", "", "G1", "G1", "G3", "G1"]


def test_a_live_stream_three_frames_late_detects_every_segment_100_ms_after_its_start(labelled: Path) -> None:
    session = Session.open(labelled)
    times = session.read_stream("video")["t_host_ns"].to_numpy(np.int64)
    truth = labels_at(session, times, "gestures")
    live = np.asarray(["G2"] * 3 + [c or "G2" for c in TRUTH[:-3]], dtype=object)  # 3 frames late, G2 in gaps
    result = agreement("labels", "class", live, truth, times)
    assert result.frames == 67 and result.segments == 3 and result.detected == 3
    assert result.accuracy == pytest.approx(1 - 9 / 67, abs=1e-4)  # the first 3 frames of each segment wrong
    assert result.delay_ms["p50"] == pytest.approx(3 * FRAME_NS / 1e6, abs=0.01)
    assert result.edit < 100.0  # the late G2 at each start is a segment of its own
    assert agreement("labels", "class", truth.copy(), truth, times).accuracy == 1.0


def test_a_segment_never_predicted_in_its_span_is_missed() -> None:
    truth = np.array([0, 0, 0, 1, 1, 2, 2, 2])
    pred = np.array([0, 0, 0, 0, 0, 2, 2, 2])
    times = np.arange(8) * 10_000_000
    assert detection_delays_ms(pred, truth, times) == [0.0, None, 0.0]


def test_a_session_without_a_live_stream_is_one_clear_error(labelled: Path) -> None:
    with pytest.raises(SessionError, match="no gestures_live stream"):
        evaluate_live(labelled)
