"""The emulators' send-time log (issue 26 item 3), so the timestamp-error benchmark cannot silently rot:
one short `midas record` of both serial emulators, and every recorded row matches exactly one logged
record by the benchmark's own matching (checked against what the emulators say they sent, and for the
trakSTAR against the values). No timing is asserted."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from midas_cli.devices.fps.emulator import FpsEmulator, FpsEmulatorConfig
from midas_cli.devices.send_log import read_send_log
from midas_cli.devices.trakstar.emulator import EmulatorConfig, TrakstarEmulator
from midas_cli.errors import ConfigError
from midas_cli.session.reader import Session
from helpers.cli import REPO, midas
from helpers.trakstar import expected_values

sys.path.insert(0, str(REPO / "benchmarks"))
import bench_timestamp_error as bench  # noqa: E402

SENSOR_COLUMNS = [f"s{s}_{a}" for s in range(1, 5) for a in ("x_mm", "y_mm", "z_mm", "azimuth_deg",
                                                              "elevation_deg", "roll_deg")]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> dict:
    folder = tmp_path_factory.mktemp("sendlog")
    trakstar = TrakstarEmulator(EmulatorConfig(link=str(folder / "emht"), send_log=str(folder / "emht.sendlog")))
    fps = FpsEmulator(FpsEmulatorConfig(link=folder / "fps", send_log=str(folder / "fps.sendlog")))
    with trakstar, fps:
        result = midas("record", "--device", f"emht=fob://{folder}/emht?rate=50&sensors=4", "--device",
                       f"fps=fps://{folder}/fps?rate=100&channels=9", "--duration", "4", "--out",
                       str(folder / "s"), "--subject", "1", "--task", "t", "--trial", "1", "--no-tui", timeout=90)
    assert result.returncode == 0, result.stderr
    session = Path(result.stdout.strip().splitlines()[-1])
    return {"session": Session.open(session), "folder": folder, "trakstar": trakstar, "fps": fps,
            "manifest": json.loads((session / "manifest.json").read_text())}


def test_the_pedal_boards_log_is_every_sample_sent_and_matches_rows_by_seq(recorded: dict) -> None:
    log = read_send_log(recorded["folder"] / "fps.sendlog")
    sent = recorded["fps"].summary()["samples"]
    logged = list(zip(log["boot"].tolist(), log["seq"].tolist()))
    assert [(s["boot"], s["seq"]) for s in sent[: len(logged)]] == logged
    assert len(sent) - len(logged) <= 2, "all but a line still queued at the stop (the pty full)"
    assert np.all(log["t_out_ns"] >= log["t_due_ns"] - 1000), "a line goes out once due, never before"
    table = recorded["session"].read_columns("fps")
    index = bench.match_fps(table, log)
    assert len(table) > 50 and np.array_equal(log["seq"][index], table["seq"])
    assert [sent[i]["t_us"] for i in index] == table["t_device_us"].tolist()


def test_the_trakstars_log_is_every_cycle_streamed_and_matches_rows_in_order(recorded: dict) -> None:
    log = read_send_log(recorded["folder"] / "emht.sendlog")
    summary = recorded["trakstar"].summary()
    assert log["cycle"].tolist() == summary["stream_counters"]
    table = recorded["session"].read_columns("emht")
    index = bench.match_emht(table, log)
    assert len(table) > 20 and index.tolist() == list(range(len(table)))
    values = np.column_stack([table[c] for c in SENSOR_COLUMNS])
    assert np.allclose(values, expected_values(recorded["trakstar"], summary, 0, len(table)).reshape(len(table), 24),
                       atol=6e-4), "row i carries cycle i's values: matching by order is exact"


def test_the_benchmarks_figures_come_out_of_a_recording(recorded: dict) -> None:
    session, anchor = recorded["session"], recorded["manifest"]["clock"]["anchor_ns"]
    for name, clock in (("fps", "t_device_us (wraps at 2^32)"), ("emht", "seq at 50 Hz (no device clock)")):
        figures = bench.stream_errors(session, name, read_send_log(recorded["folder"] / f"{name}.sendlog"), anchor)
        assert figures["clock"] == clock and figures["rows"] == len(session.read_columns(name))
        assert set(figures["raw"]) == {"mean_ms", "sd_ms", "p50_ms", "p99_ms", "max_ms"}
        assert all(np.isfinite(v) for v in figures["raw"].values()) and figures["raw"]["max_ms"] >= figures["raw"]["p99_ms"]


def test_no_send_log_is_written_unless_asked(tmp_path: Path) -> None:
    emulator = FpsEmulator(FpsEmulatorConfig(link=tmp_path / "fps"))
    with emulator:
        pass
    assert emulator.send_log is None and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("text, wanted", [("", "not an emulator send log"),
                                          ("seq,t_out_ns\n1,2\n", "not an emulator send log"),
                                          ("cycle,t_due_ns,t_out_ns\n1,2\n", "line 2: expected 3 integers"),
                                          ("cycle,t_due_ns,t_out_ns\n1,2,x\n", "line 2: expected 3 integers")])
def test_a_file_that_is_not_a_send_log_is_refused_in_one_line(tmp_path: Path, text: str, wanted: str) -> None:
    path = tmp_path / "bad.sendlog"
    path.write_text(text, encoding="ascii")
    with pytest.raises(ConfigError, match=wanted):
        read_send_log(path)
