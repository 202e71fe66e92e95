"""The soak benchmark's analysis (no timing is asserted): windows of the recorder's status lines, latency
per window only where the recorder reports it, the memory slope, first-vs-last-third latency, and the
/proc process tree it samples memory from."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks"))

import bench_soak  # noqa: E402


def status(elapsed: float, samples: int, seq_missing: int = 0, latency: dict | None = None) -> dict:
    """A status line as `midas record --status-json` prints it (one device, one stream), stamped t_s."""
    stream = {"name": "fps", "nominal_rate_hz": 850.0, "measured_rate_hz": 850.0, "samples": samples,
              "last_age_s": 0.001, "dropped": 0, "corrupt": 0, "seq_missing": seq_missing, "latest": {}}
    if latency is not None:
        stream["latency_window_ms"] = latency
    device = {"name": "fps", "kind": "fps", "url": "fps://x", "state": "ok", "reconnects": 0, "last_error": "",
              "streams": [stream]}
    return {"elapsed_s": elapsed, "t_s": elapsed + 2.0, "devices": [device]}


def test_windows_count_new_samples_losses_and_rate() -> None:
    statuses = [status(float(t), 100 * t, seq_missing=3 if t >= 45 else 0) for t in range(0, 61)]
    wins = bench_soak.windows(statuses, [], 30.0)
    assert [(w["start_s"], w["end_s"]) for w in wins] == [(0.0, 30.0), (30.0, 60.0)]
    first, second = wins[0]["streams"]["fps"], wins[1]["streams"]["fps"]
    assert first["samples"] == 3000 and first["rate_hz"] == 100.0
    assert first["seq_missing"] == 0 and second["seq_missing"] == 3
    assert "latency_ms" not in first, "no latency_window_ms in the status lines: no latency may be invented"


def test_window_latency_uses_non_overlapping_spans() -> None:
    lat = [{"p50": 1.0, "p99": 2.0 + (t == 25) * 10, "max": 3.0, "n": 100} for t in range(31)]
    statuses = [status(float(t), 100 * t, latency=lat[t]) for t in range(31)]
    result = bench_soak.window_latency(statuses[1:], "fps")
    assert result["spans"] == 3  # lines at 1, 11, 21 s: their ~10 s spans do not overlap
    assert result["n"] == 300 and result["p99"] == 2.0, "the spike at 25 s is inside the span of the 21 s line"
    statuses[21]["devices"][0]["streams"][0]["latency_window_ms"]["p99"] = 9.0
    assert bench_soak.window_latency(statuses[1:], "fps")["p99"] == 9.0
    empty = [status(float(t), 0, latency={"p50": None, "p99": None, "max": None, "n": 0}) for t in range(5)]
    assert bench_soak.window_latency(empty, "fps") is None


def sample(t: float, mib: float) -> dict:
    return {"t_s": t, "load_1min": 1.0, "processes": {"7": {"role": "recorder", "rss_mib": mib, "cpu_s": t / 2}},
            "recorder_total_mib": mib, "recorder_cpu_s": t / 2, "emulators_mib": {"fps": 50.0}, "emulators_cpu_s": t}


def test_memory_slope_leaves_out_the_warm_up() -> None:
    samples = [sample(t, 300.0 if t < 62 else 100.0 + 0.05 * t) for t in np.arange(0.0, 600.0, 5.0)]
    samples.append(sample(600.0, 900.0))  # finalising, after the last status line: not part of the slope
    summary = bench_soak.memory_summary(samples, start_s=2.0, end_s=599.0, warmup_s=60.0)
    assert summary["recorder_total"]["slope_mib_per_10min"] == pytest.approx(30.0, abs=1e-6)
    assert summary["processes"]["7"]["role"] == "recorder"
    assert summary["emulators"]["fps"]["slope_mib_per_10min"] == pytest.approx(0.0, abs=1e-9)
    window = bench_soak.window_memory(samples, 100.0, 200.0)
    assert window["recorder_cpu_percent"] == pytest.approx(50.0) and window["emulators_cpu_percent"] == 100.0


def test_latency_stability_compares_first_and_last_thirds() -> None:
    wins = [{"streams": {"fps": {"latency_ms": {"p99": p}}, "video": {}}} for p in (1, 1, 1, 2, 2, 2, 4, 4, 4)]
    result = bench_soak.latency_stability(wins)
    assert set(result) == {"fps"}
    assert result["fps"]["p99_first_third_ms"] == 1 and result["fps"]["p99_last_third_ms"] == 4
    assert result["fps"]["last_over_first"] == 4 and result["fps"]["p99_max_window_ms"] == 4


def test_process_tree_finds_a_child_and_its_memory() -> None:
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        deadline = time.monotonic() + 10
        while child.pid not in bench_soak.process_tree(bench_soak.os.getpid()) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert child.pid in bench_soak.process_tree(bench_soak.os.getpid())
        # right after exec the child holds a few KiB until the interpreter has loaded (a busy host stretches that)
        while (bench_soak.rss_kib(child.pid) or 0) <= 1000 and time.monotonic() < deadline + 20:
            time.sleep(0.05)
        assert bench_soak.rss_kib(child.pid) > 1000 and bench_soak.role(child.pid, bench_soak.os.getpid()) == "worker"
    finally:
        child.kill()
        child.wait()
    assert bench_soak.rss_kib(child.pid) is None
