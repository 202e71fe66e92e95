"""Import a session folder of the original MiDAS data-collection system (UVA-DSA/MiDAS, 2024).

Quirks handled explicitly, each counted in the import report (``logs/import_report.json`` and the
manifest's ``rig.import_report``), never silently:
* ``PDS.csv``: the header names 14 columns (no "Pedal 5 Pressure", "Pressesd" typo) but rows carry 15
  values: pressure of pedals 1..7 (-1 = the pedal's letter was absent from the serial line), pressed
  1..7 (0/1), host time ns. Read positionally, never by header. -1 pressures become empty fields.
  A serial timeout writes an all -1/0 row, indistinguishable from "nothing pressed": kept, counted.
* ``synced_data.csv``: the original 30 Hz "synced" product (LIFO pops: stale, out of order, 0/-1/-2
  placeholders). Not imported as data; its row widths and placeholders are reported; its video columns
  give the video frame clock when there is no ``video.csv`` with rows.
* ``Trakstar/trakstar.csv``: ``bytes,sensor_id,x,y,z,azimuth,elevation,roll,trakstar_time_s,host_time_ns``;
  rows sharing a trakSTAR time form one record (sensor ids 0..3 -> sensors 1..4).
* ``smartwatch_data/sw_<side>/sw_data.csv``: ``sw_epoch_ms`` is the watch clock (kept as device time,
  its offset from the host reported); ``server_epoch_ms`` holds host nanoseconds despite its name.
* Host times that repeat (coarse clock) are made strictly increasing by the smallest shift (1 ns
  steps); the raw time stays in its own column and the count is reported.
* Folder name ``<task>_S<subject>_T<trial>_<date>`` is the only metadata.
"""

from __future__ import annotations

import csv
import re
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.errors import SessionError
from midas_cli.importers.common import file_facts, strictly_increasing, write_session
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
from midas_cli.session.writer import SessionMetadata

PEDALS = 7
PDS_HEADER_14 = ["Pedal 1 Pressure", "Pedal 2 Pressure", "Pedal 3 Pressure", "Pedal 4 Pressure",
                 "Pedal 6 Pressure", "Pedal 7 Pressure"] + [f"Pedal {k} Pressed" for k in range(1, 5)] + [
                 "Pedal 5 Pressesd", "Pedal 6 Pressed", "Pedal 7 Pressed", "Computer Time"]
SYNCED_PDS_START = 26  # first column of the PDS block in synced_data.csv
_FOLDER = re.compile(r"^(?P<task>[A-Za-z0-9.-]+)_S(?P<subject>[A-Za-z0-9.-]+)_T(?P<trial>\d+)_(?P<date>\d{4}-\d{2}-\d{2})$")
_FRAME_FROM_PATH = re.compile(r"(\d+)_(\d+)\.\w+$")
RAW_HOST = Column("computer_time_ns", "int", "ns", clock="host", description="host time as the source wrote it")


def _rows(path: Path) -> tuple[list[str], list[list[str]]]:
    with open(path, newline="", encoding="utf-8") as fh:
        rows = [row for row in csv.reader(fh) if row]
    if not rows:
        raise SessionError(f"{path} is empty (expected at least a header line)")
    return rows[0], rows[1:]


def parse_folder_name(folder: Path) -> dict[str, str]:
    match = _FOLDER.match(folder.name)
    if not match:
        raise SessionError(f"{folder.name!r} is not a MiDAS session folder name "
                           "(expected <task>_S<subject>_T<trial>_<YYYY-MM-DD>)")
    return match.groupdict()


def pds_stream(path: Path, report: dict[str, Any]) -> tuple[StreamSpec, list[np.ndarray]] | None:
    """PDS.csv -> stream ``fps``: seq, t_host_ns, computer_time_ns, ch1..7_pressure (empty = -1), ch1..7_pressed."""
    header, rows = _rows(path)
    facts: dict[str, Any] = {**file_facts(path), "header_columns": len(header), "rows": len(rows)}
    report["pds"] = facts
    if not rows:
        facts["note"] = f"header only ({','.join(header)}): no pedal data recorded"
        return None
    widths = Counter(len(r) for r in rows)
    facts["row_widths"] = dict(widths)
    good = [r for r in rows if len(r) == 2 * PEDALS + 1]
    facts["malformed_rows_skipped"] = len(rows) - len(good)
    if not good:
        raise SessionError(f"{path}: no row has {2 * PEDALS + 1} values (found widths {dict(widths)})")
    if header == PDS_HEADER_14:
        facts["header_quirk"] = ("header names 14 columns (no 'Pedal 5 Pressure'), rows hold 15 values: "
                                 "read by position as pressure 1..7, pressed 1..7, host time ns")
    values = np.array([r[:-1] for r in good], dtype=float)
    pressure, pressed = values[:, :PEDALS], values[:, PEDALS:]
    raw = np.array([int(r[-1]) for r in good], dtype=np.int64)  # exact ns: never through float
    placeholder = pressure == -1
    facts["pressure_placeholders_per_pedal"] = placeholder.sum(axis=0).astype(int).tolist()
    facts["all_placeholder_rows"] = int(np.count_nonzero(placeholder.all(axis=1) & (pressed == 0).all(axis=1)))
    facts["all_placeholder_rows_meaning"] = "serial timeout or nothing pressed (indistinguishable); kept as rows"
    t_host, adjusted = strictly_increasing(raw)
    facts["host_times_adjusted"] = adjusted
    columns = [SEQ, T_HOST, RAW_HOST]
    columns += [Column(f"ch{k}_pressure", "float", "", 3, description=f"Pedal {k} pressure reading; empty = none")
                for k in range(1, PEDALS + 1)]
    columns += [Column(f"ch{k}_pressed", "int", "bool", description=f"Pedal {k} pressed (board threshold)")
                for k in range(1, PEDALS + 1)]
    spec = StreamSpec("fps", "pds", tuple(columns), 0.0, "MiDAS PDS pedal board (imported)")
    data = [np.arange(len(good), dtype=np.int64), t_host, raw, *np.where(placeholder, np.nan, pressure).T,
            *pressed.astype(np.int64).T]
    return spec, data


def trakstar_stream(path: Path, report: dict[str, Any]) -> tuple[StreamSpec, list[np.ndarray]] | None:
    """trakstar.csv -> stream ``emht`` (s1..s4 position mm, angles deg; quality not recorded -> empty)."""
    header, rows = _rows(path)
    facts: dict[str, Any] = {**file_facts(path), "rows": len(rows)}
    report["trakstar"] = facts
    if not rows:
        facts["note"] = "header only: the tracker did not run in this session; no emht stream"
        return None
    kept = [r for r in rows if len(r) == 10]
    good = np.array([r[:9] for r in kept], dtype=float)
    host_raw = np.array([int(r[9]) for r in kept], dtype=np.int64)  # exact ns: never through float
    facts["malformed_rows_skipped"] = len(rows) - len(kept)
    ids = good[:, 1].astype(int)
    base = 0 if ids.min() == 0 else 1
    facts["sensor_id_mapping"] = f"sensor id {base}..{base + 3} -> s1..s4"
    times, group = np.unique(good[:, 8], return_inverse=True)
    block = np.full((len(times), 4, 7), np.nan)
    block[group, ids - base, :6] = good[:, 2:8]
    host = np.zeros(len(times), dtype=np.int64)
    np.maximum.at(host, group, host_raw)
    order = np.argsort(host, kind="stable")
    t_host, adjusted = strictly_increasing(host[order])
    facts.update(records=len(times), host_times_adjusted=adjusted)
    spec = _emht_spec()
    return spec, [np.arange(len(times), dtype=np.int64), t_host, times[order], *block[order].reshape(len(times), 28).T]


def _emht_spec() -> StreamSpec:
    columns = [SEQ, T_HOST, Column("t_device_s", "float", "s", 6, clock="device", description="trakSTAR time")]
    for s in range(1, 5):
        columns += [Column(f"s{s}_{a}_mm", "float", "mm", 3, frame="emht_transmitter") for a in "xyz"]
        columns += [Column(f"s{s}_{a}_deg", "float", "deg", 3) for a in ("azimuth", "elevation", "roll")]
        columns.append(Column(f"s{s}_quality", "float", "", 3, description="not recorded by the source"))
    return StreamSpec("emht", "trakstar", tuple(columns), 0.0, "trakSTAR records (imported)")


def synced_facts(path: Path, report: dict[str, Any]) -> list[tuple[int, int]]:
    """Report synced_data.csv's quirks; return its video (frame, host ns) pairs (placeholders dropped)."""
    header, rows = _rows(path)
    widths = Counter(len(r) for r in rows)
    pds_values = [r[SYNCED_PDS_START:] for r in rows]
    placeholders = Counter(v for block in pds_values for v in block if v in ("0", "-1", "-2"))
    report["synced_data"] = {**file_facts(path), "header_columns": len(header), "row_widths": dict(widths),
                             "pds_block_values": sorted({len(b) for b in pds_values}),
                             "pds_block_placeholders": dict(placeholders),
                             "trakstar_rows_all_zero": sum(all(v == "0" for v in r[1:10]) for r in rows),
                             "use": "not imported as data (LIFO-synced, stale samples); video columns give "
                                    "the frame clock when video.csv has no rows"}
    frames = []
    for row in rows:
        match = _FRAME_FROM_PATH.search(row[11]) if len(row) > 11 else None
        if match and row[10] not in ("0", "-1", "-2"):
            frames.append((int(match[1]), int(row[10])))
    return frames


def video_stream(folder: Path, report: dict[str, Any]) -> tuple[StreamSpec, list[np.ndarray]] | None:
    pairs: list[tuple[int, int]] = []
    if (folder / "video.csv").is_file():
        _, rows = _rows(folder / "video.csv")
        pairs = [(int(r[0]), int(r[1])) for r in rows if len(r) >= 2]
        report["video"] = {**file_facts(folder / "video.csv"), "rows": len(rows)}
    if (folder / "synced_data.csv").is_file():
        synced = synced_facts(folder / "synced_data.csv", report)
        if not pairs:
            pairs = synced
            report.setdefault("video", {})["source"] = "synced_data.csv video_time/video_id (frame from file name)"
    if not pairs:
        return None
    frames = np.array(sorted(set(pairs)), dtype=np.int64)
    report["video"].update(frames=len(frames), first_frame=int(frames[0, 0]), duplicates_dropped=len(pairs) - len(frames))
    t_host, adjusted = strictly_increasing(frames[:, 1])
    report["video"]["host_times_adjusted"] = adjusted
    spec = StreamSpec("video", "obs", (SEQ, T_HOST, RAW_HOST), 30.0, "video frame times (imported)")
    return spec, [frames[:, 0], t_host, frames[:, 1]]


def smartwatch_streams(folder: Path, report: dict[str, Any]) -> list[tuple[StreamSpec, list[np.ndarray]]]:
    streams = []
    for path in sorted(folder.glob("smartwatch_data/sw_*/sw_data.csv")):
        side = path.parent.name.removeprefix("sw_")
        _, rows = _rows(path)
        facts: dict[str, Any] = {**file_facts(path), "rows": len(rows)}
        report[f"smartwatch_{side}"] = facts
        for sensor in sorted({r[2] for r in rows if len(r) == 7}):
            picked = [r for r in rows if len(r) == 7 and r[2] == sensor]
            watch_ms = np.array([int(r[0]) for r in picked], dtype=np.int64)
            host_raw = np.array([int(r[6]) for r in picked], dtype=np.int64)
            t_host, adjusted = strictly_increasing(host_raw)
            offset_days = float(np.median(host_raw / 1e6 - watch_ms)) / 86_400_000
            facts[sensor] = {"samples": len(picked), "host_times_adjusted": adjusted,
                             "watch_clock_behind_host_days": round(offset_days, 3),
                             "note": "server_epoch_ms holds host ns; sw_epoch_ms is the watch clock"}
            columns = (SEQ, T_HOST, RAW_HOST, Column("t_watch_ms", "int", "ms", clock="device", description="watch clock"),
                       *(Column(f"{a}", "float", "", 6, frame="watch") for a in ("x", "y", "z")))
            spec = StreamSpec(f"smartwatch_{side}_{sensor}", f"smartwatch_{side}", columns, 0.0, f"{side} watch {sensor}")
            values = np.array([[float(v) for v in r[3:6]] for r in picked])
            streams.append((spec, [np.arange(len(picked), dtype=np.int64), t_host, host_raw, watch_ms, *values.T]))
    return streams


def import_midas_dcs(folder: Path | str, out_root: Path | str, platform: str = "unknown") -> tuple[Path, dict[str, Any]]:
    """Import one original MiDAS session folder; returns (new session path, import report)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SessionError(f"{folder} is not a folder")
    meta = parse_folder_name(folder)
    report: dict[str, Any] = {"source": str(folder), "format": "midas-dcs (UVA-DSA/MiDAS 2024)",
                              "folder_metadata": meta}
    streams = []
    video = video_stream(folder, report)
    streams += [video] if video else []
    for path, reader in ((folder / "PDS.csv", pds_stream), (folder / "Trakstar" / "trakstar.csv", trakstar_stream)):
        found = reader(path, report) if path.is_file() else None
        streams += [found] if found else []
    streams += smartwatch_streams(folder, report)
    streams = [(s, c) for s, c in streams if len(c[0])]
    if not streams:
        raise SessionError(f"{folder} holds no samples in any stream (see the report: {report})")
    devices = {spec.device: {"kind": spec.device, "url": f"import://{folder.name}/{spec.name}",
                             "settings": {"imported": True}, "streams": [spec.name]} for spec, _ in streams}
    metadata = SessionMetadata(meta["subject"], meta["task"], int(meta["trial"]), platform,
                               f"imported from MiDAS folder {folder.name} (recorded {meta['date']})")
    return write_session(Path(out_root), metadata, devices, streams, report), report
