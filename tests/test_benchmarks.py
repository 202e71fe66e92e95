"""The benchmark harness's own correctness (no timing is asserted anywhere): the align benchmark's fast
session generator writes exactly what StreamSpec.format_rows would, and its equality check between
`midas align` and the merge_asof baseline passes on real output and catches a changed value."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import bench_align  # noqa: E402

from midas_cli.analysis.align import AlignOptions, align_and_write  # noqa: E402
from midas_cli.devices.registry import describe_device  # noqa: E402


def test_vectorised_rows_match_format_rows() -> None:
    spec = describe_device("handkp", bench_align.URLS["handkp"]).streams[0]
    k = np.arange(40, dtype=np.int64)
    host = 1_800_000_000_000_000_000 + k * 33_333_333
    text = bench_align.format_chunk(spec, k, host, np.random.default_rng(3))
    rows = [line.split(",") for line in text.splitlines()]
    assert any(field == "" for row in rows for field in row), "handkp gaps must be written as empty fields"
    parsed = [tuple(int(v) if c.dtype == "int" else (float(v) if v else float("nan"))
                    for c, v in zip(spec.columns, row)) for row in rows]
    assert spec.format_rows(parsed) == text


def test_compare_accepts_midas_output_and_catches_a_changed_value(tmp_path: Path) -> None:
    session = bench_align.write_session(tmp_path / "s", minutes=0.05)
    align_and_write(session, AlignOptions())
    baseline = tmp_path / "baseline.csv"
    script = tmp_path / "baseline.py"
    script.write_text(bench_align.BASELINE, encoding="utf-8")
    subprocess.run([sys.executable, str(script), str(session), str(baseline), "3.0"], check=True)
    check = bench_align.compare(session, baseline)
    assert check["equal"] and check["columns_compared"] >= 60 and check["frames"] == 90
    frame = pd.read_csv(baseline)
    frame.loc[10, "fps.ch3_adc"] += 1
    frame.to_csv(baseline, index=False)
    assert bench_align.compare(session, baseline)["mismatched_columns"] == ["fps.ch3_adc"]
