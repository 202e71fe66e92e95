"""What every export format needs from a session: units per column, the frame clock, the label sets."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np

from midas_cli.session.labels import list_label_sets, read_frame_labels
from midas_cli.session.reader import Session

log = logging.getLogger(__name__)

FRAME_STREAM = "video"  # labels/*.csv count frames in the seq of this stream (session/labels.py)


def column_facts(session: Session, name: str) -> list[dict[str, Any]]:
    """One entry per column of stream ``name``: name, dtype, unit, description (and clock/frame if set)."""
    return [{"unit": column.unit, **column.to_manifest()} for column in session.stream_spec(name).columns]


def device_kind(session: Session, name: str) -> str:
    """The kind of the device that recorded stream ``name`` (the manifest's ``devices``), else its device name."""
    spec = session.stream_spec(name)
    return str((session.manifest.get("devices", {}).get(spec.device) or {}).get("kind") or spec.device)


def units(session: Session, name: str) -> dict[str, str]:
    return {column.name: column.unit for column in session.stream_spec(name).columns}


@dataclass
class FrameClock:
    """The session's frame clock: video frame ``seq`` -> host time (ns)."""

    seq: np.ndarray
    t_host_ns: np.ndarray

    def times_of(self, frames: np.ndarray) -> np.ndarray:
        """Host ns of each frame; -1 where the video stream has no such frame."""
        order = np.argsort(self.seq, kind="stable")
        seq = self.seq[order]
        at = np.clip(np.searchsorted(seq, frames), 0, max(len(seq) - 1, 0))
        found = (seq[at] == frames) if len(seq) else np.zeros(len(frames), dtype=bool)
        return np.where(found, self.t_host_ns[order][at] if len(seq) else -1, -1).astype(np.int64)


def frame_clock(session: Session) -> FrameClock | None:
    """The video stream's (seq, t_host_ns), read piece by piece (two int64 per frame are kept), or None
    when the session has no video stream."""
    if FRAME_STREAM not in session.stream_names:
        return None
    seq, times = [], []
    for chunk in session.iter_stream(FRAME_STREAM):
        seq.append(chunk["seq"].to_numpy(np.int64))
        times.append(chunk["t_host_ns"].to_numpy(np.int64))
    return FrameClock(np.concatenate(seq), np.concatenate(times))


@dataclass
class TimedLabels:
    """One label set with each labelled frame's host time (frames the frame clock lacks are left out)."""

    name: str
    frames: np.ndarray
    labels: np.ndarray
    t_host_ns: np.ndarray
    meta: dict[str, Any]
    left_out: int


def label_sets(session: Session, clock: FrameClock | None) -> Iterator[TimedLabels]:
    """Every label set of the session, timed on the frame clock. Without a frame clock (no video stream)
    none can be timed: a warning says so."""
    for name in list_label_sets(session.path):
        labels = read_frame_labels(session.path, name)
        if clock is None:
            log.warning("%s: label set %s left out: no %r stream to time its frames", session.path, name, FRAME_STREAM)
            continue
        times = clock.times_of(labels.frames)
        keep = times >= 0
        if not keep.all():
            log.warning("%s: label set %s: %d frame(s) not in the %r stream left out", session.path, name,
                        int((~keep).sum()), FRAME_STREAM)
        yield TimedLabels(name, labels.frames[keep], labels.labels[keep], times[keep], labels.meta, int((~keep).sum()))


def json_columns(chunk: Any) -> list[list[Any]]:
    """The columns of a stream piece as lists of Python values (int, float, str, None for a missing value):
    what a JSON encoder writes exactly (floats by repr, ints in full)."""
    columns = []
    for name in chunk.columns:
        series = chunk[name]
        missing = series.isna().to_numpy()
        if series.dtype == object:  # a text column
            columns.append([None if m else v for v, m in zip(series.tolist(), missing)])
            continue
        values = series.to_numpy(dtype=object, na_value=None) if series.dtype.kind in "iu" or str(series.dtype) == "Int64" \
            else series.to_numpy(dtype=np.float64).tolist()
        if not isinstance(values, list):
            values = [None if m else int(v) for v, m in zip(values, missing)]
        elif missing.any():
            values = [None if m else v for v, m in zip(values, missing)]
        columns.append(values)
    return columns
