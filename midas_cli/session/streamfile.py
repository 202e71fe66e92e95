"""Reading back one per-stream CSV file: integrity facts shared by finalize, verify and repair."""

from __future__ import annotations

import hashlib
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.session.csvtext import count_separators, separator_mask, separators_per_line
from midas_cli.session.schema import StreamSpec
from midas_cli.session.values import read_regular_file

MAX_LISTED_GAPS = 200


def file_sha256(path: Path) -> str:
    """sha256 of a file's bytes, read in 1 MiB blocks (no whole-file copy in memory)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@dataclass
class StreamSummary:
    """What a stream file holds. Times are host-clock Unix-epoch ns."""

    samples: int = 0
    bytes: int = 0
    sha256: str = ""
    header_ok: bool = True
    first_t_host_ns: int | None = None
    last_t_host_ns: int | None = None
    measured_rate_hz: float | None = None
    seq_gap_count: int = 0
    seq_missing: int = 0
    seq_resets: int = 0
    seq_gaps: list[dict[str, int]] = field(default_factory=list)
    t_host_nonincreasing: int = 0
    bad_lines: list[int] = field(default_factory=list)
    torn_tail_bytes: int = 0

    def manifest_fields(self) -> dict[str, Any]:
        """The per-stream manifest entries that describe the finished file."""
        return {
            "samples": self.samples,
            "bytes": self.bytes,
            "sha256": self.sha256,
            "first_t_host_ns": self.first_t_host_ns,
            "last_t_host_ns": self.last_t_host_ns,
            "measured_rate_hz": None if self.measured_rate_hz is None else round(self.measured_rate_hz, 3),
            "seq_gaps": {
                "count": self.seq_gap_count,
                "missing": self.seq_missing,
                "resets": self.seq_resets,
                "listed": self.seq_gaps,
            },
        }


def summarize_stream(path: Path, spec: StreamSpec) -> StreamSummary:
    """Hash and parse ``path``: sample count, field-count errors, torn tail, sequence gaps, time order."""
    return summarize_bytes(read_regular_file(path), spec)


def summarize_bytes(data: bytes, spec: StreamSpec) -> StreamSummary:
    """``summarize_stream`` of a stream file's bytes. Values that do not parse leave the times and
    sequence facts unset; ``values.parse_stream_bytes`` says which value and where."""
    summary = StreamSummary(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
    header_end = data.find(b"\n")
    if header_end < 0:
        summary.header_ok = False
        summary.torn_tail_bytes = len(data)
        return summary
    summary.header_ok = data[: header_end + 1].decode("utf-8", "replace") == spec.header_line()
    body_end = data.rfind(b"\n") + 1
    summary.torn_tail_bytes = len(data) - body_end
    body = data[header_end + 1 : body_end]
    summary.bad_lines = _lines_with_wrong_width(body, len(spec.columns))
    if not body or summary.bad_lines:
        summary.samples = body.count(b"\n")
        return summary
    try:
        seq, t_host = read_seq_and_time(body)
    except (ValueError, TypeError, OverflowError):  # text, overflow, missing values: not a time or a count
        summary.samples = body.count(b"\n")
        return summary
    _fill_time_and_sequence(summary, seq, t_host)
    return summary


def read_seq_and_time(body: bytes) -> tuple[np.ndarray, np.ndarray]:
    """The first two columns (seq, t_host_ns) of header-less CSV ``body`` as int64 arrays."""
    import pandas as pd  # here, not at the top: recorder workers import this module and never call it

    frame = pd.read_csv(io.BytesIO(body), header=None, usecols=[0, 1], dtype="int64", engine="c")
    return frame[0].to_numpy(), frame[1].to_numpy()


def complete_line_end(data: bytes, width: int) -> int:
    """Byte offset just past the last line of ``data`` that is complete and has ``width`` fields."""
    end = data.rfind(b"\n") + 1
    while end > 0:
        start = data.rfind(b"\n", 0, end - 1) + 1
        if count_separators(data[start:end]) == width - 1 or start == 0:
            return end
        end = start
    return 0


def _lines_with_wrong_width(body: bytes, width: int) -> list[int]:
    """1-based data-line numbers whose field count differs from ``width`` (at most 20 listed)."""
    if not body:
        return []
    raw = np.frombuffer(body, dtype=np.uint8)
    per_line = separators_per_line(separator_mask(raw), np.flatnonzero(raw == ord("\n")))
    return [int(i) + 1 for i in np.flatnonzero(per_line != width - 1)[:20]]


MIN_RATE_SPAN_S = 0.1  # the shortest first-to-last span a measured rate is given for


def _fill_time_and_sequence(summary: StreamSummary, seq: np.ndarray, t_host: np.ndarray) -> None:
    summary.samples = len(seq)
    summary.first_t_host_ns = int(t_host[0])
    summary.last_t_host_ns = int(t_host[-1])
    span = (summary.last_t_host_ns - summary.first_t_host_ns) / 1e9
    # a rate over a burst (rows a device delivered at once: a late open, a buffer flushed) means nothing
    summary.measured_rate_hz = (len(seq) - 1) / span if span >= MIN_RATE_SPAN_S else None
    summary.t_host_nonincreasing = int(np.count_nonzero(np.diff(t_host) <= 0))
    step = np.diff(seq)
    jumps = np.flatnonzero(step != 1)
    summary.seq_gap_count = int(np.count_nonzero(step > 1))
    summary.seq_missing = int(np.sum(step[step > 1] - 1))
    summary.seq_resets = int(np.count_nonzero(step < 1))
    summary.seq_gaps = [
        {"after_seq": int(seq[i]), "next_seq": int(seq[i + 1]), "t_host_ns": int(t_host[i + 1])}
        for i in jumps[:MAX_LISTED_GAPS]
    ]
