"""`midas import midas-dcs|jigsaws|compass`: quirks handled and reported, sessions verify."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from midas_cli.importers.midas_dcs import PDS_HEADER_14
from midas_cli.session.integrity import verify_session
from midas_cli.session.labels import read_frame_labels
from midas_cli.session.reader import Session
from helpers.cli import SHARED_DATA, midas

SAMPLE_NAME = "midas-dcs-sample/trakt_Strakt_T1_2024-07-05"
SAMPLE = SHARED_DATA / SAMPLE_NAME
T0 = 1720199364203926800


def _import(*args: str) -> Path:
    result = midas("import", *args, check=True)
    return Path(result.stdout.split()[-1])


@pytest.mark.shared_data(SAMPLE_NAME)
def test_real_midas_folder_imports_and_verifies(tmp_path: Path) -> None:
    session_path = _import("midas-dcs", str(SAMPLE), "--out", str(tmp_path))
    assert midas("session", "verify", str(session_path)).returncode == 0
    session = Session.open(session_path)
    fps = session.read_stream("fps")
    assert [f"ch{k}_pressure" for k in range(1, 8)] == list(fps.columns[3:10])
    assert fps[[f"ch{k}_pressure" for k in range(1, 8)]].isna().all().all()  # -1 placeholders -> empty
    assert (fps[[f"ch{k}_pressed" for k in range(1, 8)]] == 0).all().all()
    report = session.manifest["rig"]["import_report"]
    assert report["pds"]["host_times_adjusted"] == 40 and report["pds"]["all_placeholder_rows"] == 300
    assert report["synced_data"]["row_widths"] == {"41": 300}
    assert session.metadata["subject"] == "trakt" and session.metadata["trial"] == 1
    aligned = midas("align", str(session_path), "--json")
    assert aligned.returncode == 0, aligned.stderr
    assert (session_path / "derived" / "aligned.npz").is_file()


def _write_dcs_folder(root: Path) -> Path:
    folder = root / "pegs_S7_T3_2024-07-19"
    (folder / "Trakstar").mkdir(parents=True)
    rows = [",".join(PDS_HEADER_14)]
    for i in range(6):  # pedal 5 (absent from the header) pressed in rows 2..3
        pressure = ["-1"] * 7
        pressed = ["0"] * 7
        if i in (2, 3):
            pressure[4], pressed[4] = "512.0", "1"
        rows.append(",".join(pressure + pressed + [str(T0 + (i // 2) * 1_000_000)]))  # repeated times
    rows.append("1,2,3")  # a torn row
    (folder / "PDS.csv").write_text("\n".join(rows) + "\n")
    track = ["Bytes,SensorID,x,y,z,azimuth,elevation,roll,TrakStar Time,Computer Time"]
    for record in range(2):
        for sensor in range(4):
            track.append(f"54,{sensor},{sensor * 10 + record},1,2,3,4,5,{100.0 + record / 240},{T0 + record * 4_000_000 + sensor}")
    (folder / "Trakstar" / "trakstar.csv").write_text("\n".join(track) + "\n")
    header = "server_time,trakstar_SensorID,trakstar_Status,trakstar_x,trakstar_y,trakstar_z,trakstar_azimuth,trakstar_elevation,trakstar_roll,trakstar_atime,video_time,video_id,3d_camera_time,3d_camera_frame_id,smartwatch_1_time,smartwatch_1_wrist_position,smartwatch_1_sensor_type,smartwatch_1_value_X_Axis,smartwatch_1_value_Y_Axis,smartwatch_1_value_Z_Axis,smartwatch_2_time,smartwatch_2_wrist_position,smartwatch_2_sensor_type,smartwatch_2_value_X_Axis,smartwatch_2_value_Y_Axis,smartwatch_2_value_Z_Axis,PDS_time,pedal_1,pedal_2,pedal_3,pedal_4,pedal_5,pedal_6,pedal_7"  # noqa: E501 - the original system's header, as it writes it
    synced = [header]
    for frame in range(4):
        video = [str(T0 + frame * 33_333_333), f"./Data/x/imgs/{frame}_{T0 + frame * 33_333_333}.png"] if frame != 2 else ["0", "0"]
        synced.append(",".join([str(T0 + frame)] + ["0"] * 9 + video + ["0"] * 14 + ["-1"] * 7 + ["0"] * 7 + [str(T0)]))
    (folder / "synced_data.csv").write_text("\n".join(synced) + "\n")
    return folder


def test_synthetic_midas_folder_puts_each_pedal_in_its_column(tmp_path: Path) -> None:
    session_path = _import("midas-dcs", str(_write_dcs_folder(tmp_path)), "--out", str(tmp_path / "out"))
    assert verify_session(session_path).ok
    session = Session.open(session_path)
    fps = session.read_stream("fps")
    assert fps["ch5_pressure"].tolist()[2:4] == [512.0, 512.0] and fps["ch5_pressed"].tolist() == [0, 0, 1, 1, 0, 0]
    assert fps["ch4_pressure"].isna().all() and fps["ch6_pressure"].isna().all()  # no shift by one pedal
    assert (np.diff(fps["t_host_ns"]) > 0).all() and fps["computer_time_ns"].iloc[1] == T0  # raw time kept
    emht = session.read_stream("emht")
    assert len(emht) == 2 and emht["s1_x_mm"].tolist() == [0.0, 1.0] and emht["s4_x_mm"].tolist() == [30.0, 31.0]
    assert session.read_stream("video")["seq"].tolist() == [0, 1, 3]  # the 0-placeholder row is not a frame
    report = json.loads((session_path / "logs" / "import_report.json").read_text())
    assert report["pds"]["malformed_rows_skipped"] == 1 and report["pds"]["host_times_adjusted"] == 3
    assert session.metadata["task"] == "pegs" and session.metadata["subject"] == "7"


def test_bad_folder_name_is_a_session_error(tmp_path: Path) -> None:
    (tmp_path / "not-midas").mkdir()
    result = midas("import", "midas-dcs", str(tmp_path / "not-midas"), "--out", str(tmp_path / "o"))
    assert result.returncode == 4 and "<task>_S<subject>_T<trial>" in result.stderr


def _arm_rows(n: int, rotation_values: bool) -> np.ndarray:
    t = np.arange(n)[:, None]
    position = 0.01 * np.hstack([t, 2 * t, 3 * t])  # metres
    orientation = np.tile(np.eye(3).ravel(), (n, 1)) if rotation_values else np.tile([0, 0, 0, 1.0], (n, 1))
    return position, orientation


def test_jigsaws_files_become_sessions_with_labels(tmp_path: Path) -> None:
    source = tmp_path / "Suturing"
    (source / "kinematics" / "AllGestures").mkdir(parents=True)
    (source / "transcriptions").mkdir()
    n = 12
    position, rotation = _arm_rows(n, True)
    arm = np.hstack([position, rotation, np.zeros((n, 6)), np.full((n, 1), 0.5)])  # 19 columns
    np.savetxt(source / "kinematics" / "AllGestures" / "Suturing_B001.txt", np.hstack([arm] * 4), fmt="%.6f")
    (source / "transcriptions" / "Suturing_B001.txt").write_text("2 5 G1 \r\n6 10 G2 \r\n")
    session_path = _import("jigsaws", str(source), "--out", str(tmp_path / "out"))
    assert verify_session(session_path).ok
    mtm = Session.open(session_path).read_stream("mtm")
    assert mtm["left_y_mm"].tolist()[:3] == [0.0, 20.0, 40.0] and mtm["left_qw"].iloc[0] == 1.0
    assert abs(mtm["right_grasper_deg"].iloc[0] - np.degrees(0.5)) < 1e-3 and mtm["clutch"].isna().all()
    labels = read_frame_labels(session_path)
    assert labels.labels.tolist() == [""] * 2 + ["G1"] * 4 + ["G2"] * 5 + [""]


def test_compass_csv_becomes_mtm_and_psm_streams(tmp_path: Path) -> None:
    source = tmp_path / "Suturing"
    (source / "kinematics").mkdir(parents=True)
    (source / "gestures").mkdir()
    n = 8
    position, quaternion = _arm_rows(n, False)
    arm = np.hstack([position, quaternion, np.full((n, 1), 0.2)])
    names = [f"{a}_{c}" for a in ("MTML", "MTMR", "PSML", "PSMR") for c in ("x", "y", "z", "qx", "qy", "qz", "qw", "g")]
    np.savetxt(source / "kinematics" / "Suturing_S02_T01.csv", np.hstack([arm] * 4), delimiter=",",
               header=",".join(names), comments="", fmt="%.6f")
    (source / "gestures" / "Suturing_S02_T01.txt").write_text("0 7 G3\r\n")
    session_path = _import("compass", str(source), "--out", str(tmp_path / "out"))
    session = Session.open(session_path)
    psm = session.read_stream("psm")
    assert psm["right_z_mm"].tolist()[:2] == [0.0, 30.0] and abs(psm["right_vz_mm_s"].iloc[3] - 900.0) < 1e-6
    assert session.metadata["subject"] == "02" and session.metadata["trial"] == 1
    assert read_frame_labels(session_path).classes() == ["G3"]
