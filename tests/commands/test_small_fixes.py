"""Issue 14, small things users hit: the JIGSAWS import summary, `session list` order, the
processing-speed column of `extract pedals`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from midas_cli.clock import HostClock
from midas_cli.session.reader import Session
from midas_cli.session.writer import SessionMetadata, SessionWriter
from midas_cli.simulate.console_video import render_console_video
from midas_cli.synthetic.console_video import ConsoleVideoSpec
from helpers.cli import SPEC, midas


def test_jigsaws_summary_names_its_files_and_the_device_is_a_davinci(tmp_path: Path) -> None:
    source = tmp_path / "Suturing"
    (source / "kinematics" / "AllGestures").mkdir(parents=True)
    (source / "transcriptions").mkdir()
    arm = np.hstack([np.zeros((5, 3)), np.tile(np.eye(3).ravel(), (5, 1)), np.zeros((5, 7))])  # 19 columns
    np.savetxt(source / "kinematics" / "AllGestures" / "Suturing_B001.txt", np.hstack([arm] * 4), fmt="%.6f")
    (source / "transcriptions" / "Suturing_B001.txt").write_text("0 4 G1\n")
    result = midas("import", "jigsaws", str(source), "--out", str(tmp_path / "out"), check=True)
    lines = {line.split(":", 1)[0].strip(): line.split(":", 1)[1].strip() for line in result.stderr.splitlines()
             if ":" in line and line.startswith("  ")}
    assert lines["kinematics"].startswith("Suturing_B001.txt"), result.stderr
    assert lines["kinematics"] and lines["transcription"], result.stderr  # no empty values
    assert "Suturing_B001.txt" in lines["transcription"]
    manifest = Session.open(Path(result.stdout.split()[-1])).manifest
    assert manifest["devices"]["robot"]["kind"] == "davinci"


def _session(root: Path, trial: int) -> Path:
    writer = SessionWriter.create(root, SessionMetadata("1", "pegs", trial), HostClock(10**18),
                                  {"demo": {"kind": "demo"}}, [SPEC])
    writer.finalize("complete", "test", 10**18, {})
    return writer.folder


def test_session_list_sorts_trial_numbers_naturally(tmp_path: Path) -> None:
    for trial in (10, 2, 1):
        _session(tmp_path, trial)
    result = midas("session", "list", str(tmp_path), "--paths", check=True)
    trials = [Path(p).name.split("_")[2] for p in result.stdout.split()]
    assert trials == ["T1", "T2", "T10"]


def test_ground_truth_table_names_processing_speed_not_fps(tmp_path: Path) -> None:
    video = render_console_video(tmp_path / "c.avi", ConsoleVideoSpec(2.0, 1, size=(320, 180))).video
    result = midas("ground-truth", "pedals", str(video), check=True)  # the old spelling still works, and warns
    assert result.stderr.startswith("midas: warning: `midas ground-truth` is now `midas extract pedals`")
    header_lines = [line for line in result.stdout.splitlines() if "┃" in line]
    cells = {cell.strip() for line in header_lines for cell in line.split("┃")}
    assert "fps" not in cells and {"processed", "processed frames/s"} & cells, header_lines
