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
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from midas_cli.errors import SessionError
from midas_cli.importers.common import (Segment, file_facts, rate_hz, recording_of, split_rows, strictly_increasing,
                                       write_session)
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


def _rows(path: Path) -> tuple[list[str], list[list[str]], list[int]]:
    """Header, data rows and each data row's 1-based line number (blank lines skipped)."""
    rows, lines = [], []
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.reader(fh)
        for row in reader:
            if row:
                rows.append(row)
                lines.append(reader.line_num)
    if not rows:
        raise SessionError(f"{path} is empty (expected at least a header line)")
    return rows[0], rows[1:], lines[1:]


def parse_folder_name(folder: Path) -> dict[str, str]:
    match = _FOLDER.match(folder.name)
    if not match:
        raise SessionError(f"{folder.name!r} is not a MiDAS session folder name "
                           "(expected <task>_S<subject>_T<trial>_<YYYY-MM-DD>)")
    return match.groupdict()


# host time (ns) of a data row, per source file: the column that tells one recording from another
HOST_TIME: dict[str, Callable[[list[str]], str]] = {
    "pds": lambda row: row[-1], "synced_data": lambda row: row[0], "trakstar": lambda row: row[-1],
    "video": lambda row: row[1] if len(row) > 1 else "", "smartwatch": lambda row: row[-1]}


@dataclass
class SourceFile:
    """One CSV of the folder, cut into segments (one per recording it holds)."""

    key: str  # report key: pds, synced_data, trakstar, video, smartwatch_<side>
    path: Path
    name: str  # path inside the folder, as discontinuities name it
    header: list[str]
    segments: list[Segment]


def read_sources(folder: Path, discontinuities: list[dict[str, Any]]) -> list[SourceFile]:
    """Every source CSV of the folder, checked for host-time order and row shape."""
    candidates = [("video", folder / "video.csv"), ("synced_data", folder / "synced_data.csv"),
                  ("pds", folder / "PDS.csv"), ("trakstar", folder / "Trakstar" / "trakstar.csv")]
    candidates += [(f"smartwatch_{p.parent.name.removeprefix('sw_')}", p)
                   for p in sorted(folder.glob("smartwatch_data/sw_*/sw_data.csv"))]
    sources = []
    for key, path in candidates:
        if not path.is_file():
            continue
        header, rows, lines = _rows(path)
        name = str(path.relative_to(folder))
        kind = "smartwatch" if key.startswith("smartwatch_") else key
        segments, found = split_rows(name, rows, lines, HOST_TIME[kind])
        discontinuities += found
        sources.append(SourceFile(key, path, name, header, segments))
    return sources


def pds_stream(path: Path, header: list[str], rows: list[list[str]], facts: dict[str, Any]
               ) -> tuple[StreamSpec, list[np.ndarray]] | None:
    """PDS.csv rows -> stream ``fps``: seq, t_host_ns, computer_time_ns, ch1..7_pressure (empty = -1), ch1..7_pressed."""
    facts.update(header_columns=len(header), rows=len(rows))
    if not rows:
        facts["note"] = f"header only ({','.join(header)}): no pedal data recorded"
        return None
    widths = Counter(len(r) for r in rows)
    facts["row_widths"] = dict(widths)
    good = [r for r in rows if len(r) == 2 * PEDALS + 1]
    facts["malformed_rows_skipped"] = len(rows) - len(good) + facts.get("partial_lines_dropped", 0)
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
    spec = StreamSpec("fps", "pds", tuple(columns), rate_hz(t_host), "MiDAS PDS pedal board (imported)")
    data = [np.arange(len(good), dtype=np.int64), t_host, raw, *np.where(placeholder, np.nan, pressure).T,
            *pressed.astype(np.int64).T]
    return spec, data


def trakstar_stream(rows: list[list[str]], facts: dict[str, Any]) -> tuple[StreamSpec, list[np.ndarray]] | None:
    """trakstar.csv rows -> stream ``emht`` (s1..s4 position mm, angles deg; quality not recorded -> empty)."""
    facts["rows"] = len(rows)
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
    spec = _emht_spec(rate_hz(t_host))
    return spec, [np.arange(len(times), dtype=np.int64), t_host, times[order], *block[order].reshape(len(times), 28).T]


def _emht_spec(rate: float | None) -> StreamSpec:
    columns = [SEQ, T_HOST, Column("t_device_s", "float", "s", 6, clock="device", description="trakSTAR time")]
    for s in range(1, 5):
        columns += [Column(f"s{s}_{a}_mm", "float", "mm", 3, frame="emht_transmitter") for a in "xyz"]
        columns += [Column(f"s{s}_{a}_deg", "float", "deg", 3) for a in ("azimuth", "elevation", "roll")]
        columns.append(Column(f"s{s}_quality", "float", "", 3, description="not recorded by the source"))
    return StreamSpec("emht", "trakstar", tuple(columns), rate, "trakSTAR records (imported)")


def synced_facts(header: list[str], rows: list[list[str]], facts: dict[str, Any]) -> list[tuple[int, int]]:
    """Report synced_data.csv's quirks; return its video (frame, host ns) pairs (placeholders dropped).

    Its pedal block is read by the row's width: 8 values (PDS time + 7 pedals, as the header says:
    0/-1/-2 are "no new sample" placeholders) or 15 (pressure 1..7 with -1 = none, pressed 1..7 as
    real 0/1 values, host time)."""
    widths = Counter(len(r) for r in rows)
    placeholders: Counter[str] = Counter()
    pressed: Counter[str] = Counter()
    for row in rows:
        block = row[SYNCED_PDS_START:]
        if len(block) == 2 * PEDALS + 1:
            placeholders.update(v for v in block[:PEDALS] if v == "-1")
            pressed.update(block[PEDALS:2 * PEDALS])
        else:
            placeholders.update(v for v in block if v in ("0", "-1", "-2"))
    facts.update(header_columns=len(header), row_widths=dict(widths),
                 pds_block_values=sorted({len(r[SYNCED_PDS_START:]) for r in rows}),
                 pds_block_placeholders=dict(placeholders), pds_block_pressed_values=dict(pressed),
                 trakstar_rows_all_zero=sum(all(v == "0" for v in r[1:10]) for r in rows),
                 use="not imported as data (LIFO-synced, stale samples); video columns give "
                     "the frame clock when video.csv has no rows")
    frames = []
    for row in rows:
        match = _FRAME_FROM_PATH.search(row[11]) if len(row) > 11 else None
        if match and row[10] not in ("0", "-1", "-2"):
            frames.append((int(match[1]), int(row[10])))
    return frames


def video_stream(video_rows: list[list[str]] | None, synced: list[tuple[int, int]],
                 report: dict[str, Any]) -> tuple[StreamSpec, list[np.ndarray]] | None:
    pairs = [(int(r[0]), int(r[1])) for r in video_rows or [] if len(r) >= 2]
    if not pairs and synced:
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


def smartwatch_streams(side: str, rows: list[list[str]], facts: dict[str, Any]
                       ) -> list[tuple[StreamSpec, list[np.ndarray]]]:
    streams = []
    facts["rows"] = len(rows)
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
        spec = StreamSpec(f"smartwatch_{side}_{sensor}", f"smartwatch_{side}", columns, rate_hz(t_host),
                          f"{side} watch {sensor}")
        values = np.array([[float(v) for v in r[3:6]] for r in picked])
        streams.append((spec, [np.arange(len(picked), dtype=np.int64), t_host, host_raw, watch_ms, *values.T]))
    return streams


def recordings(sources: list[SourceFile]) -> list[dict[str, Segment]]:
    """The recordings the folder holds: per recording, each file's segment that belongs to it. The
    file cut into the most segments defines them; other files' segments join by host time."""
    cut = [s for s in sources if s.segments]
    if not cut:
        return [{}]
    reference = max(cut, key=lambda s: len(s.segments)).segments
    found: list[dict[str, Segment]] = [{} for _ in reference]
    for source in cut:
        for segment in source.segments:
            chosen = found[recording_of(segment, reference)]
            if source.key in chosen:
                raise SessionError(f"{source.path}: two parts (lines {chosen[source.key].lines[0]} and "
                                   f"{segment.lines[0]}) fall in one recording's time span; cannot tell the "
                                   "recordings apart: split the folder by hand")
            chosen[source.key] = segment
    return found


def build_streams(sources: list[SourceFile], parts: dict[str, Segment], report: dict[str, Any],
                  discontinuities: list[dict[str, Any]]) -> list[tuple[StreamSpec, list[np.ndarray]]]:
    """The streams of one recording from its segment of each file (a file without one adds its facts)."""
    streams: list[tuple[StreamSpec, list[np.ndarray]]] = []
    by_key = {s.key: s for s in sources}
    for source in sources:
        segment = parts.get(source.key)
        facts = report[source.key] = file_facts(source.path)
        if segment is not None and len(source.segments) > 1:
            facts["lines"] = f"{segment.lines[0]}-{segment.lines[-1]}"
        partial = sum(d["what"].startswith("partial line") for d in discontinuities if d["file"] == source.name)
        if partial:
            facts["partial_lines_dropped"] = partial
        rows = segment.rows if segment else []
        if source.key == "pds":
            found = pds_stream(source.path, source.header, rows, facts)
            streams += [found] if found else []
        elif source.key == "trakstar":
            found = trakstar_stream(rows, facts)
            streams += [found] if found else []
        elif source.key.startswith("smartwatch_"):
            streams += smartwatch_streams(source.key.removeprefix("smartwatch_"), rows, facts)
        elif source.key == "video":
            facts["rows"] = len(rows)
    synced = parts.get("synced_data")
    frames = synced_facts(by_key["synced_data"].header, synced.rows, report["synced_data"]) if synced else []
    video = video_stream(parts["video"].rows if "video" in parts else None, frames, report)
    return ([video] if video else []) + streams


def import_midas_dcs(folder: Path | str, out_root: Path | str, platform: str = "unknown", split: bool = False
                     ) -> list[tuple[Path, dict[str, Any]]]:
    """Import one original MiDAS session folder; returns (new session path, import report) per recording.

    A folder into which several recordings were written at once (host time going back, row shape
    changing) is refused unless ``split``, which writes one session per recording."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SessionError(f"{folder} is not a folder")
    meta = parse_folder_name(folder)
    discontinuities: list[dict[str, Any]] = []
    sources = read_sources(folder, discontinuities)
    parts = recordings(sources)
    if len(parts) > 1 and not split:
        cuts = [d for d in discontinuities if d["what"].endswith("a new recording")]
        where = "; ".join(f"{d['file']} line {d['line']}: {d['what'].removesuffix(': a new recording')}" for d in cuts)
        raise SessionError(f"{folder} holds {len(parts)} recordings written into one folder ({where}): "
                           "import them as separate sessions with --split-recordings")
    built = []
    for index, recording in enumerate(parts):
        report: dict[str, Any] = {"source": str(folder), "format": "midas-dcs (UVA-DSA/MiDAS 2024)",
                                  "folder_metadata": meta, "discontinuities": discontinuities}
        if len(parts) > 1:
            report["recording"] = f"{index + 1} of {len(parts)} in the folder (split at the discontinuities)"
        streams = [(s, c) for s, c in build_streams(sources, recording, report, discontinuities) if len(c[0])]
        built.append((index, streams, report))
    empty = [index + 1 for index, streams, _ in built if not streams]
    if len(empty) == len(built):
        raise SessionError(f"{folder} holds no samples in any stream (see the report: {built[0][2]})")
    results = []
    for index, streams, report in built:
        if not streams:
            continue
        if empty:
            report["recordings_without_samples"] = empty  # not written: nothing to import
        devices = {spec.device: {"kind": spec.device, "url": f"import://{folder.name}/{spec.name}",
                                 "settings": {"imported": True}, "streams": [spec.name]} for spec, _ in streams}
        note = f"imported from MiDAS folder {folder.name} (recorded {meta['date']})"
        metadata = SessionMetadata(meta["subject"], meta["task"], int(meta["trial"]), platform,
                                   note + (f", recording {index + 1} of {len(parts)}" if len(parts) > 1 else ""))
        results.append((write_session(Path(out_root), metadata, devices, streams, report), report))
    return results
