"""Issue 14: a MiDAS folder into which two acquisition servers wrote at once (host time going back,
a partial line, the column block changing mid-file) is refused, or split into one session per
recording with --split-recordings; every discontinuity is reported with file and line. Built at test time
from the shared sample (two real folders spliced into one)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from midas_cli.session.reader import Session
from helpers.cli import SHARED_DATA, midas

SAMPLES = SHARED_DATA / "midas-dcs-sample"
FIRST, SECOND = SAMPLES / "trakt_Strakt_T1_2024-07-05", SAMPLES / "smart_Ssmartwatch_T2_2024-07-02"
pytestmark = pytest.mark.shared_data("midas-dcs-sample/trakt_Strakt_T1_2024-07-05", "midas-dcs-sample/smart_Ssmartwatch_T2_2024-07-02")


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


def spliced_folder(root: Path) -> Path:
    """FIRST with SECOND's recording written into the same files after it: synced_data.csv gets a
    partial line then SECOND's 34-value rows (3 days earlier); PDS.csv gets FIRST's pedal rows again,
    stamped on SECOND's host clock; SECOND's smartwatch files are added."""
    folder = root / FIRST.name
    shutil.copytree(FIRST, folder)
    for path in folder.rglob("*"):
        path.chmod(0o755 if path.is_dir() else 0o644)
    synced = _lines(folder / "synced_data.csv")
    second = _lines(SECOND / "synced_data.csv")[1:]
    partial = synced[-1][: len(synced[-1]) // 2].rstrip(",")  # a row torn off half way
    (folder / "synced_data.csv").write_text("\n".join(synced + [partial] + second) + "\n")
    pds = _lines(folder / "PDS.csv")
    shift = int(second[0].split(",")[0]) - int(pds[1].split(",")[-1])
    again = [",".join(row.split(",")[:-1] + [str(int(row.split(",")[-1]) + shift)]) for row in pds[1:]]
    (folder / "PDS.csv").write_text("\n".join(pds + again) + "\n")
    shutil.copytree(SECOND / "smartwatch_data", folder / "smartwatch_data")
    return folder


def test_spliced_folder_is_refused_naming_each_cut(tmp_path: Path) -> None:
    result = midas("import", "midas-dcs", str(spliced_folder(tmp_path)), "--out", str(tmp_path / "out"))
    assert result.returncode == 4, result.stderr
    message = result.stderr.strip()
    assert len(message.splitlines()) == 1 and "holds 2 recordings" in message and "--split-recordings" in message
    assert "synced_data.csv line 303: row shape changes from 41 to 34 values" in message
    assert "PDS.csv line 302: host time jumps back by" in message
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_split_writes_one_session_per_recording(tmp_path: Path) -> None:
    folder = spliced_folder(tmp_path)
    result = midas("import", "midas-dcs", str(folder), "--out", str(tmp_path / "out"), "--split-recordings", "--json",
                   check=True)
    imported = json.loads(result.stdout)
    assert len(imported) == 2
    first, second = (Session.open(item["path"]) for item in imported)
    assert set(first.stream_names) == {"video", "fps"}
    assert set(second.stream_names) == {"fps", "smartwatch_left_acc"}  # its synced rows carry no video frame
    fps1, fps2 = first.read_stream("fps"), second.read_stream("fps")
    assert len(fps1) == len(fps2) == 300
    assert fps1["computer_time_ns"].max() < fps1["computer_time_ns"].min() + 10**10  # no 3-day span: not merged
    assert fps2["computer_time_ns"].min() < fps1["computer_time_ns"].min() - 2 * 86_400 * 10**9
    report1, report2 = (item["import_report"] for item in imported)
    what = {(d["file"], d["line"]): d["what"] for d in report1["discontinuities"]}
    assert what[("synced_data.csv", 302)].startswith("partial line")
    assert what[("synced_data.csv", 303)].startswith("row shape changes from 41 to 34")
    assert what[("PDS.csv", 302)].startswith("host time jumps back by")
    # the 15-value pedal block holds real pressed values (0), not placeholders; the 8-value block holds -2
    assert report1["synced_data"]["row_widths"] == {"41": 300}
    assert "0" not in report1["synced_data"]["pds_block_placeholders"]
    assert report1["synced_data"]["pds_block_pressed_values"] == {"0": 300 * 7}
    assert report2["synced_data"]["row_widths"] == {"34": 101}
    assert report2["synced_data"]["pds_block_placeholders"] == {"-2": 101 * 8}
    assert report1["recording"].startswith("1 of 2") and report2["recording"].startswith("2 of 2")
    again = midas("import", "midas-dcs", str(folder), "--out", str(tmp_path / "again"), "--split", check=True)
    assert "discontinuity: synced_data.csv line 302: partial line" in again.stderr  # the old name still works
    assert again.stderr.startswith("midas: warning: --split is now --split-recordings")
    assert midas("session", "verify", imported[1]["path"]).returncode == 0


def test_clean_sample_has_no_discontinuities(tmp_path: Path) -> None:
    result = midas("import", "midas-dcs", str(FIRST), "--out", str(tmp_path), "--json", check=True)
    (item,) = json.loads(result.stdout)
    assert item["import_report"]["discontinuities"] == [] and "recording" not in item["import_report"]
    assert np.isclose(Session.open(item["path"]).stream_spec("fps").nominal_rate_hz, 299 / 5.9134205, rtol=1e-3)


def test_jigsaws_file_with_a_partial_line_is_refused_naming_it(tmp_path: Path) -> None:
    source = tmp_path / "Suturing"
    (source / "kinematics" / "AllGestures").mkdir(parents=True)
    lines = [" ".join(["0.1"] * 76)] * 6
    lines[3] = " ".join(["0.1"] * 40)  # torn mid-row
    (source / "kinematics" / "AllGestures" / "Suturing_B001.txt").write_text("\n".join(lines) + "\n")
    result = midas("import", "jigsaws", str(source), "--out", str(tmp_path / "out"))
    assert result.returncode == 4, result.stderr
    assert "Suturing_B001.txt" in result.stderr and "line 4: 40 values where jigsaws kinematics have 76" in result.stderr


def test_small_steps_back_are_reported_and_kept_large_ones_cut() -> None:
    from midas_cli.importers.common import split_rows

    s = 10**9
    times = [100 * s, 101 * s, 101 * s - 2_000_000, 102 * s, 50 * s, 51 * s]
    rows = [["1", "2", str(t)] for t in times]
    rows.insert(3, ["1", str(102 * s)])  # torn line
    segments, found = split_rows("f.csv", rows, list(range(2, 2 + len(rows))), lambda r: r[-1])
    assert [len(seg.rows) for seg in segments] == [4, 2]
    assert [(d["line"], d["what"].split(" (")[0].split(" by")[0]) for d in found] == [
        (4, "host time goes back"), (5, "partial line"), (7, "host time jumps back")]
