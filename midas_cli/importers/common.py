"""Helpers shared by the importers: strictly increasing host times, cutting a file where a new recording
starts (host time back, row shape change, partial lines), writing a whole session at once."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from midas_cli.clock import HostClock
from midas_cli.session import artifacts
from midas_cli.session.schema import StreamSpec
from midas_cli.session.writer import SessionMetadata, SessionWriter

CHUNK_ROWS = 20_000
REPORT_FILE = "logs/import_report.json"


def strictly_increasing(raw_ns: np.ndarray) -> tuple[np.ndarray, int]:
    """(t_host_ns, adjusted): the smallest strictly increasing times >= the raw ones: a time
    that does not exceed its predecessor becomes predecessor + 1 ns
    or later (sources stamped with a coarse clock repeat values). ``adjusted`` counts the moved samples; callers
    keep the raw time in its own column and report the count."""
    raw = np.asarray(raw_ns, dtype=np.int64)
    index = np.arange(len(raw), dtype=np.int64)
    times = np.maximum.accumulate(raw - index) + index if len(raw) else raw.copy()  # smallest such sequence
    return times, int(np.count_nonzero(times != raw))


def file_facts(path: Path) -> dict[str, Any]:
    data = Path(path).read_bytes()
    return {"path": str(path), "bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}


def write_session(out_root: Path, metadata: SessionMetadata, devices: dict[str, dict[str, Any]],
                  streams: list[tuple[StreamSpec, list[np.ndarray]]], report: dict[str, Any]) -> Path:
    """Create a session holding ``streams`` ((spec, column arrays) each, ints as int64, missing = NaN),
    the import report in the manifest's rig (``import_report``) and in ``logs/import_report.json``."""
    starts = [int(cols[1][0]) for _, cols in streams if len(cols[1])]
    stops = [int(cols[1][-1]) for _, cols in streams if len(cols[1])]
    start_ns = min(starts) if starts else 0
    writer = SessionWriter.create(out_root, metadata, HostClock(0), devices, [s for s, _ in streams],
                                  {"imported": True, "import_report": report}, start_ns=start_ns)
    for spec, columns in streams:
        for begin in range(0, len(columns[0]), CHUNK_ROWS):
            parts = [c[begin:begin + CHUNK_ROWS].tolist() for c in columns]
            writer.append(spec.name, spec.format_rows(list(zip(*parts))))
    writer.finalize("complete", "imported", max(stops) if stops else start_ns, {})
    artifacts.write_json(writer.folder, REPORT_FILE, report)
    return writer.folder


def rate_hz(t_host_ns: np.ndarray) -> float | None:
    """Mean sample rate (Hz) of host times (ns), or None with fewer than two distinct times: the
    nominal rate of an imported stream whose source does not state one."""
    if len(t_host_ns) < 2 or t_host_ns[-1] <= t_host_ns[0]:
        return None
    return round((len(t_host_ns) - 1) * 1e9 / float(t_host_ns[-1] - t_host_ns[0]), 3)


@dataclass
class Segment:
    """Consecutive data rows of one source file with one row shape and host times that never go back.
    ``lines`` are the rows' 1-based line numbers in the file; times are host ns as the source wrote them."""

    file: str
    lines: list[int] = field(default_factory=list)
    rows: list[list[str]] = field(default_factory=list)
    t_first: int = 0
    t_last: int = 0

    @property
    def width(self) -> int:
        return len(self.rows[0]) if self.rows else 0

    def add(self, line: int, row: list[str], t_ns: int) -> None:
        if not self.rows:
            self.t_first = t_ns
        self.lines.append(line)
        self.rows.append(row)
        self.t_last = max(self.t_last, t_ns)


NEW_RECORDING_BACK_NS = 1_000_000_000  # host time going back further than this starts a new recording


def split_rows(file: str, rows: list[list[str]], lines: list[int], host_time: Callable[[list[str]], str]
               ) -> tuple[list[Segment], list[dict[str, Any]]]:
    """Cut a file's data rows where a new recording starts: host time (``host_time(row)``, integer ns)
    jumping back by more than a second (a smaller step back is reported and kept: out of order), or the
    row shape changing for good. A row whose width matches neither its
    neighbours', or whose host time is not an integer, is a partial line: dropped. Returns the segments
    (in file order) and every discontinuity as {file, line, what}."""
    segments: list[Segment] = []
    found: list[dict[str, Any]] = []
    current: Segment | None = None
    for i, (line, row) in enumerate(zip(lines, rows)):
        t_ns = _int_or_none(host_time(row)) if row else None
        next_width = len(rows[i + 1]) if i + 1 < len(rows) else None
        if current is not None and len(row) != current.width and next_width != len(row) or t_ns is None:
            width = current.width if current else next_width
            found.append({"file": file, "line": line,
                          "what": f"partial line ({len(row)} values where the rows around it have {width}): dropped"})
            continue
        if current is None or len(row) != current.width:
            if current is not None:
                found.append({"file": file, "line": line,
                              "what": f"row shape changes from {current.width} to {len(row)} values: a new recording"})
        elif t_ns < current.t_last - NEW_RECORDING_BACK_NS:
            found.append({"file": file, "line": line, "what": f"host time jumps back by "
                          f"{(current.t_last - t_ns) / 1e9:.3f} s: a new recording"})
        else:
            if t_ns < current.t_last:
                found.append({"file": file, "line": line, "what": f"host time goes back by "
                              f"{(current.t_last - t_ns) / 1e9:.6f} s: out of order, kept"})
            current.add(line, row, t_ns)
            continue
        current = Segment(file)
        segments.append(current)
        current.add(line, row, t_ns)
    return segments, found


def _int_or_none(text: str) -> int | None:
    try:
        return int(text)
    except (TypeError, ValueError):
        return None


def recording_of(segment: Segment, reference: list[Segment]) -> int:
    """Index of the reference segment (one per recording) that ``segment`` belongs to: the one its host
    time range overlaps most, else the nearest in time."""
    def score(ref: Segment) -> tuple[int, int]:
        overlap = min(segment.t_last, ref.t_last) - max(segment.t_first, ref.t_first)
        return (overlap, 0) if overlap >= 0 else (-1, overlap)
    return max(range(len(reference)), key=lambda k: score(reference[k]))
