"""Helpers shared by the importers: strictly increasing host times, writing a whole session at once."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

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
