"""`midas align`: association, masks, gap filling, downsampling, lag estimation, written files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from midas_cli.analysis.align import AlignOptions, align_and_write
from midas_cli.analysis.sync import associate, cubic_spline, downsample_rows, estimate_lag, fill_gaps
from midas_cli.session.derived import read_aligned
from helpers.analysis_sessions import raven_session
from helpers.cli import midas

MS = 1_000_000


def test_causal_takes_latest_sample_at_or_before_the_frame() -> None:
    samples = np.array([0, 10, 20, 30]) * MS
    frames = np.array([-5, 0, 9, 10, 14, 16, 95]) * MS
    idx, valid, delta = associate(samples, frames, "causal", stale_ns=25 * MS)
    assert valid.tolist() == [False, True, True, True, True, True, False]  # before start / too stale
    assert idx[valid].tolist() == [0, 0, 1, 1, 1]
    assert delta[valid].tolist() == [0.0, -9.0, 0.0, -4.0, -6.0]
    assert np.isnan(delta[0]) and np.isnan(delta[-1])


def test_nearest_takes_the_closest_sample_either_side() -> None:
    samples = np.array([0, 10, 20]) * MS
    frames = np.array([-2, 4, 6, 19]) * MS
    idx, valid, delta = associate(samples, frames, "nearest", stale_ns=5 * MS)
    assert idx.tolist() == [0, 0, 1, 2]
    assert valid.all()
    assert delta.tolist() == [2.0, -4.0, 4.0, 1.0]


def test_gap_filling_spline_for_short_gaps_forward_fill_for_long() -> None:
    t = np.arange(0, 4.0, 0.1)
    values = np.column_stack([t ** 2, -t])
    values[[0, 1]] = np.nan  # leading gap: nothing to fill from
    values[10:14] = np.nan  # 0.5 s gap: spline
    values[20:35] = np.nan  # 1.6 s gap: forward fill
    filled, code = fill_gaps(t, values, max_spline_gap_s=1.0)
    assert code[:2].tolist() == [-1, -1] and np.isnan(filled[:2]).all()
    assert (code[10:14] == 1).all()
    np.testing.assert_allclose(filled[10:14], np.column_stack([t[10:14] ** 2, -t[10:14]]), atol=1e-6)
    assert (code[20:35] == 2).all()
    np.testing.assert_array_equal(filled[20:35], np.repeat(values[19:20], 15, axis=0))
    assert (code[35:] == 0).all()


@pytest.mark.parametrize("knots", [2, 3, 4, 7, 500])
def test_gap_spline_is_scipys_not_a_knot_cubic_spline(knots: int) -> None:
    """align fills gaps without importing scipy.interpolate; the curve must stay CubicSpline's (uneven knots,
    several columns, between knots and beyond both ends)."""
    from scipy.interpolate import CubicSpline

    rng = np.random.default_rng(knots)
    x = np.cumsum(rng.uniform(0.01, 0.2, knots))
    y = rng.normal(size=(knots, 3)) * [1, 100, 1e-3]
    at = np.concatenate([rng.uniform(x[0] - 0.3, x[-1] + 0.3, 300), x])
    expected = CubicSpline(x, y, axis=0)(at)
    np.testing.assert_allclose(cubic_spline(x, y, at), expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())


def test_downsampling_keeps_first_frame_of_each_bin() -> None:
    t_ns = (np.arange(30) * 1e9 / 30).astype(np.int64)
    assert downsample_rows(t_ns, 10.0).tolist() == list(range(0, 30, 3))
    assert len(downsample_rows(t_ns, None)) == 30


def test_lag_estimator_recovers_a_sub_sample_shift() -> None:
    rng = np.random.default_rng(1)
    t = np.arange(0, 60, 1 / 30)
    signal = np.convolve(rng.normal(size=len(t) + 200), np.ones(15) / 15, mode="same")
    late = np.interp(t - 0.05, t, signal[: len(t)])  # 50 ms late = 1.5 frames
    assert estimate_lag(signal[: len(t)], late, 30.0) == pytest.approx(0.05, abs=0.01)


def test_align_cli_writes_masked_table_with_features(tmp_path: Path) -> None:
    session = raven_session(tmp_path, duration_s=20.0, latency_ms=40.0)
    result = midas("align", str(session), "--json", "--csv", check=True)
    summary = json.loads(result.stdout)[0]
    table = read_aligned(session)
    assert summary["frames"] == len(table.frame) == 600
    assert table.frame.tolist() == list(range(600))
    emht_delta = table.column("emht_delta_ms")
    assert np.isnan(emht_delta[:2]).all()  # EmHT rows start 40 ms after the first frame: masked, not filled
    assert np.nanmax(emht_delta) <= 0 and np.nanmin(emht_delta) > -1000 / 240 - 1e-6
    for name in ("emht.left_hand_x_mm", "emht.right_grasper_mm", "emht.left_vx_mm_s", "handkp.left_hand_x_mm",
                 "handkp.left_filled", "clutch", "mtm.left_yaw_deg"):
        assert table.has(name), name
    assert set(np.unique(table.column("handkp.left_filled")[~np.isnan(table.column("handkp.left_filled"))])) <= {0, 1, 2}
    csv = pd.read_csv(session / "derived" / "aligned.csv")
    assert csv["emht.s1_x_mm"].isna().sum() == int((~table.mask[:, table.columns.index("emht.s1_x_mm")]).sum())
    meta = json.loads((session / "derived" / "aligned.json").read_text())
    assert meta["method"] == "causal" and meta["sources"]["emht"]
    assert {c["name"]: c["unit"] for c in meta["columns"]}["emht.left_vx_mm_s"] == "mm/s"


def test_aligned_lag_estimate_within_one_frame_of_injected_latency(tmp_path: Path) -> None:
    session = raven_session(tmp_path, duration_s=30.0, latency_ms=60.0)
    align_and_write(session, AlignOptions(rate_hz=30.0))
    table = read_aligned(session)
    em = np.column_stack([table.column(f"emht.left_hand_{a}_mm") for a in "xyz"])
    robot = np.column_stack([table.column(f"mtm.left_{a}_mm") for a in "xyz"])
    speed = lambda p: np.r_[np.nan, np.linalg.norm(np.diff(p, axis=0), axis=1)]  # noqa: E731
    lag = estimate_lag(speed(robot), speed(em), 30.0)
    assert abs(lag - 0.060) < 1 / 30


def test_align_refuses_a_session_without_video(small_session: Path) -> None:
    result = midas("align", str(small_session))
    assert result.returncode == 4
    assert "video" in result.stderr


def test_downsampling_keeps_regular_frames_despite_ns_rounding() -> None:
    from midas_cli.analysis.sync import downsample_rows

    frame_ns = np.round(np.arange(90) * 1e9 / 30).astype(np.int64)  # frame 3 is at 99 999 999 ns
    assert downsample_rows(frame_ns, 10.0).tolist() == list(range(0, 90, 3))


def _short_video_session(root: Path, video_s: float = 1.0, demo_s: float = 10.0) -> Path:
    """A 30 Hz video clock of ``video_s`` at the start of a 100 Hz ``demo`` stream of ``demo_s``."""
    from midas_cli.clock import HostClock
    from midas_cli.session.schema import SEQ, T_HOST, StreamSpec
    from midas_cli.session.writer import SessionMetadata, SessionWriter
    from helpers.cli import SPEC

    video = StreamSpec("video", "video", (SEQ, T_HOST), 30.0, "video frame times")
    t0 = 1_720_000_000 * 10**9
    writer = SessionWriter.create(root, SessionMetadata("1", "pegs", 1), HostClock(t0),
                                  {"video": {"kind": "video"}, "demo": {"kind": "demo"}}, [video, SPEC], start_ns=t0)
    frames = int(video_s * 30)
    writer.append("video", video.format_rows([(i, t0 + round(i * 1e9 / 30)) for i in range(frames)]))
    writer.append("demo", SPEC.format_rows([(i, t0 + i * 10 * MS, float(i)) for i in range(int(demo_s * 100))]))
    writer.finalize("complete", "test", t0 + int(demo_s * 1e9), {})
    return writer.folder


def test_align_reports_coverage_and_warns_when_the_video_clock_covers_a_fraction(tmp_path: Path) -> None:
    session = _short_video_session(tmp_path)
    result = midas("align", str(session), "--json", check=True)
    summary = json.loads(result.stdout)[0]
    assert summary["frames"] == 30
    assert summary["coverage"]["demo"] == {"samples_share": 0.097, "span_share": 0.0968}  # 97 of 1000; 0.967 of 9.99 s
    warnings = [line for line in result.stderr.splitlines() if "warning" in line]
    assert len(warnings) == 1 and "'demo'" in warnings[0] and "9.7%" in warnings[0] and "97 of 1000" in warnings[0]
    meta = json.loads((session / "derived" / "aligned.json").read_text())
    assert meta["coverage"]["demo"]["samples_inside"] == 97 and meta["coverage"]["demo"]["samples"] == 1000


def test_align_onto_a_regular_clock_spanning_the_recording(tmp_path: Path) -> None:
    session = _short_video_session(tmp_path)
    result = midas("align", str(session), "--clock", "30", "--json", check=True)
    summary = json.loads(result.stdout)[0]
    assert summary["frames"] == 301  # demo samples over 9.99 s -> ticks 0..300 at 30 Hz (the last at 10 s)
    assert summary["coverage"]["demo"]["samples_share"] == 1.0 and "warning" not in result.stderr
    table = read_aligned(session)
    assert np.diff(table.t_host_ns).min() >= 33_333_333 and np.diff(table.t_host_ns).max() <= 33_333_334
    assert not np.isnan(table.column("demo.x_mm")).any()  # every tick has a fresh demo sample
    assert np.isnan(table.column("video_delta_ms")[40:]).all()  # the video stream is just another stream here
    assert json.loads((session / "derived" / "aligned.json").read_text())["clock_hz"] == 30.0
    assert midas("align", str(session), "--clock", "fast").returncode == 2


def test_align_without_video_needs_a_regular_clock(small_session: Path) -> None:
    refused = midas("align", str(small_session))
    assert refused.returncode == 4 and "no 'video' stream" in refused.stderr and "--clock" in refused.stderr
    result = midas("align", str(small_session), "--clock", "50", "--json", check=True)
    assert json.loads(result.stdout)[0]["frames"] > 1


def test_default_alignment_of_a_fully_covered_session_says_nothing(tmp_path: Path) -> None:
    session = raven_session(tmp_path, duration_s=5.0, latency_ms=10.0)
    result = midas("align", str(session), "--json", check=True)
    assert "warning" not in result.stderr
    assert all(c["samples_share"] >= 0.95 for c in json.loads(result.stdout)[0]["coverage"].values())


def test_downsample_is_the_flag_and_rate_its_old_name_with_a_warning(tmp_path: Path) -> None:
    """issue 18: `--rate` means a device's sample rate everywhere; align's frame-clock downsampling is
    `--downsample` (the old name still works, saying so; both at once is a usage error)."""
    session = raven_session(tmp_path, duration_s=4.0)
    new = midas("align", str(session), "--downsample", "10", "--json", check=True)
    assert json.loads(new.stdout)[0]["frames"] == 40 and "warning" not in new.stderr
    old = midas("align", str(session), "--rate", "10", "--json", check=True)
    assert json.loads(old.stdout)[0]["frames"] == 40
    assert "--rate is now --downsample" in old.stderr
    both = midas("align", str(session), "--rate", "10", "--downsample", "10")
    assert both.returncode == 2 and both.stderr.strip().splitlines() == [
        "midas: error: --rate is the old name of --downsample: give only --downsample"]
    assert "--rate" not in midas("align", "--help").stdout.replace("--clock", "")
