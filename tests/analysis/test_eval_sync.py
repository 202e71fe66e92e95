"""`midas eval sync` (issue 26 item 2): offsets between modalities from events both see, validated on
simulated sessions whose EmHT is late by a known latency and drifts by a known rate."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from helpers.cli import midas


def _simulate(out: Path, seconds: int, *extra: str) -> Path:
    made = midas("simulate", "dataset", "--platform", "raven-ii", "--trials", "1", "--max-seconds", str(seconds),
                 "--out", str(out), *extra, check=True)
    return Path(made.stdout.split()[-1])


def test_a_25_ms_offset_is_recovered_within_2_ms_and_judged(tmp_path: Path) -> None:
    session = _simulate(tmp_path / "sim", 60, "--latency-ms", "25")
    result = midas("eval", "sync", str(session), "--threshold-ms", "20", "--json")
    assert result.returncode == 0, result.stderr
    pairs = {p["pair"]: p for p in json.loads(result.stdout)}
    assert set(pairs) == {"mtm~emht", "psm~emht"}
    for pair in pairs.values():
        assert pair["offset_ms"] == pytest.approx(25.0, abs=2.0) and pair["n"] == 6
        assert pair["verdict"] == ("ok" if pair["worst_ms"] <= 20 else "over 20 ms")
    table = json.loads((session / "derived" / "eval" / "sync.json").read_text())
    assert table["provenance"]["threshold_ms"] == 20
    assert (session / "derived" / "plots" / "sync.png").stat().st_size > 0
    strict = midas("eval", "sync", str(session), "--threshold-ms", "5", "--json", "--no-plots")
    assert {p["verdict"] for p in json.loads(strict.stdout)} == {"over 5 ms"}


@pytest.mark.slow
def test_a_50_ppm_drift_is_recovered(tmp_path: Path) -> None:
    session = _simulate(tmp_path / "sim", 240, "--latency-ms", "25", "--emht-drift-ppm", "50")
    result = midas("eval", "sync", str(session), "--json", "--no-plots")
    pair = next(p for p in json.loads(result.stdout) if p["pair"] == "mtm~emht")
    assert pair["drift_ppm"] == pytest.approx(50, abs=15)
    t, ms = np.array(pair["windows"]).T
    assert np.polyval(np.polyfit(t, ms, 1), 0.0) == pytest.approx(25.0, abs=2.0)  # the offset at the start


def test_a_session_with_nothing_shared_is_exit_4_and_bad_options_exit_2(tmp_path: Path) -> None:
    from helpers.cli import write_session

    lone = write_session(tmp_path / "lone")
    result = midas("eval", "sync", str(lone))
    assert result.returncode == 4 and "nothing two modalities both see" in result.stderr
    assert [line for line in result.stderr.splitlines() if not line.startswith("measuring ")] == \
        [result.stderr.splitlines()[-1]]  # one error line (after the progress line)
    bad = midas("eval", "sync", str(lone), "--threshold-ms", "nan")
    assert bad.returncode == 2 and "--threshold-ms" in bad.stderr


def test_the_sync_statement_says_how_and_what_was_measured(tmp_path: Path) -> None:
    """Manifest at finalisation (the method, each stream's clocks), then session info and the Parquet export
    with the clock fits and measured offsets once align and eval sync have run."""
    import pyarrow.parquet as pq

    session = _simulate(tmp_path / "sim", 20, "--latency-ms", "25")
    manifest = json.loads((session / "manifest.json").read_text())
    assert manifest["sync"]["method"].startswith("simulated") and manifest["sync"]["streams"]["fps"]["device_clock"] == "t_device_us"
    before = json.loads(midas("session", "info", str(session), "--json", check=True).stdout)["sync"]
    assert before["measured_offsets"].startswith("not measured") and before["streams"]["emht"]["fit"].startswith("not")
    midas("align", str(session), check=True)
    midas("eval", "sync", str(session), "--no-plots", "--threshold-ms", "50", check=True)
    after = json.loads(midas("session", "info", str(session), "--json", check=True).stdout)["sync"]
    assert {o["pair"] for o in after["measured_offsets"]} == {"mtm~emht", "psm~emht"}
    assert all(o["verdict"] == "ok" for o in after["measured_offsets"])
    assert after["streams"]["emht"]["fit"]["clock"] == "t_device_s"
    midas("export", str(session), "--format", "parquet", "--out", str(tmp_path / "x"), check=True)
    meta = pq.read_schema(tmp_path / "x" / session.name / "emht.parquet").metadata
    assert json.loads(meta[b"midas.sync"]) == after
    recorded = midas("record", "--simulate", "--duration", "1", "--no-tui", "--out", str(tmp_path / "rec"),
                     "--subject", "1", "--task", "t", "--trial", "1", check=True)
    live = json.loads((Path(recorded.stdout.splitlines()[-1]) / "manifest.json").read_text())["sync"]
    assert live["method"].startswith("software timestamping on one clock") and live["streams"]["emht"]["stamp"]
