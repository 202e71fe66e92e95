"""The segment model: gesture segments in seconds or frames -> one label per video frame, and back.

Frame convention (the one of ``midas_cli.session.labels``): frame ``i`` is the 0-based index of a
frame in the recording, the ``seq`` of the session's ``video`` stream, and covers the video time
``[i/fps, (i+1)/fps)`` (constant frame rate; the stream's ``t_device_s`` timecode is checked against
it). Rounding rule: a frame gets a segment's label when the frame's midpoint ``(i + 0.5)/fps`` lies in
the segment's ``[start, end)``; so a segment ``[1.0 s, 2.0 s)`` at 30 fps labels frames 30..59. (The
original MiDAS pipeline joined 0-based labels to 1-based frame numbers and shifted every label one
frame late; the tests pin this convention.)
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Sequence

import numpy as np

from midas_cli.errors import SessionError

GAP_MODES = ("unlabelled", "idle")
OVERLAP_RULES = ("later", "earlier", "error")


@dataclass(frozen=True)
class TimedSegment:
    """A gesture from an annotation tool: ``[start_s, end_s)`` in video seconds; ``source`` names it."""

    label: str
    start_s: float
    end_s: float
    source: str


@dataclass(frozen=True)
class FrameSegment:
    """A gesture over frames ``first..last`` (0-based, inclusive); ``source`` names where it came from."""

    label: str
    first: int
    last: int
    source: str

    @property
    def frames(self) -> int:
        return self.last - self.first + 1


@dataclass(frozen=True)
class FrameClock:
    """The session's video frames: ``seqs`` (N,) ascending 0-based frame indices, ``fps`` in Hz."""

    seqs: np.ndarray
    fps: float

    def first_frame(self, t_s: float) -> int:
        """First frame whose midpoint is at or after ``t_s`` (video seconds)."""
        return math.ceil(t_s * self.fps - 0.5)

    def to_frames(self, seg: TimedSegment) -> FrameSegment | None:
        """Frames whose midpoint lies in ``[start_s, end_s)``; None when it covers no midpoint."""
        first, stop = self.first_frame(seg.start_s), self.first_frame(seg.end_s)
        return FrameSegment(seg.label, first, stop - 1, seg.source) if stop > first else None

    def seconds(self, first: int, last: int) -> tuple[float, float]:
        """``[start, end)`` in video seconds of frames ``first..last`` (inclusive)."""
        return first / self.fps, (last + 1) / self.fps


@dataclass
class RasterReport:
    """What happened while turning segments into frame labels (every list holds JSON-able dicts)."""

    segments: int = 0
    overlaps: list[dict[str, Any]] = field(default_factory=list)
    gaps: list[dict[str, Any]] = field(default_factory=list)
    clipped: list[dict[str, Any]] = field(default_factory=list)
    dropped: list[dict[str, Any]] = field(default_factory=list)
    skipped: list[dict[str, Any]] = field(default_factory=list)
    gap_mode: str = "unlabelled"
    overlap_rule: str = "later"
    frame_counts: dict[str, int] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def rasterize(segments: Sequence[FrameSegment], seqs: np.ndarray, overlap_rule: str = "later",
              gap_mode: str = "unlabelled", idle: str | None = None) -> tuple[np.ndarray, RasterReport]:
    """One label per frame of ``seqs`` (N,) from ``segments``: clip to the recorded frames, resolve
    overlaps by ``overlap_rule`` (later/earlier-starting segment wins, or error), and fill frames no
    segment covers with '' (``gap_mode`` unlabelled) or the ``idle`` class. Returns labels (N,) object."""
    if overlap_rule not in OVERLAP_RULES or gap_mode not in GAP_MODES:
        raise SessionError(f"overlap rule must be one of {OVERLAP_RULES}, gaps one of {GAP_MODES}")
    if gap_mode == "idle" and not idle:
        raise SessionError("--gaps idle needs a taxonomy with an idle class; use --gaps unlabelled")
    if len(seqs) == 0:
        raise SessionError("the session's video stream has no frames to label")
    report = RasterReport(segments=len(segments), gap_mode=gap_mode, overlap_rule=overlap_rule)
    kept = _clip(sorted(segments, key=lambda s: (s.first, s.last)), int(seqs[0]), int(seqs[-1]), report)
    report.overlaps = find_overlaps(kept)
    if report.overlaps and overlap_rule == "error":
        first = report.overlaps[0]
        raise SessionError(f"{len(report.overlaps)} overlapping segment pair(s), first {first['a']} and "
                           f"{first['b']} share frames {first['first']}..{first['last']}; fix the annotation "
                           "or choose --overlap later|earlier")
    labels = np.full(len(seqs), "", dtype=object)
    for seg in (kept if overlap_rule == "later" else kept[::-1]):
        lo, hi = np.searchsorted(seqs, seg.first, "left"), np.searchsorted(seqs, seg.last, "right")
        labels[lo:hi] = seg.label
    report.gaps = find_gaps(labels, seqs)
    if gap_mode == "idle":
        labels[labels == ""] = idle
    names, counts = np.unique(labels, return_counts=True)
    report.frame_counts = {str(n) or "(unlabelled)": int(c) for n, c in zip(names, counts)}
    return labels, report


def _clip(segments: list[FrameSegment], lo: int, hi: int, report: RasterReport) -> list[FrameSegment]:
    """Cut segments to the recorded frames ``lo..hi``; clipped and dropped ones go into ``report``."""
    kept = []
    for seg in segments:
        entry = {"segment": seg.source, "label": seg.label, "first": seg.first, "last": seg.last}
        if seg.first > hi or seg.last < lo:
            report.dropped.append({**entry, "reason": "after the video's last frame" if seg.first > hi
                                   else "before the video's first recorded frame"})
            continue
        first, last = max(seg.first, lo), min(seg.last, hi)
        if (first, last) != (seg.first, seg.last):
            report.clipped.append({**entry, "frames_cut": seg.frames - (last - first + 1),
                                   "side": _side(seg.first < lo, seg.last > hi), "video_frames": [lo, hi]})
        kept.append(FrameSegment(seg.label, first, last, seg.source))
    return kept


def _side(at_start: bool, at_end: bool) -> str:
    return "both" if at_start and at_end else "start" if at_start else "end"


def find_overlaps(segments: Sequence[FrameSegment]) -> list[dict[str, Any]]:
    """Pairs of segments (sorted by first frame) that claim a common frame."""
    found = []
    for i, a in enumerate(segments):
        for b in segments[i + 1:]:
            if b.first > a.last:
                break
            found.append({"a": a.source, "b": b.source, "labels": [a.label, b.label],
                          "first": b.first, "last": min(a.last, b.last), "frames": min(a.last, b.last) - b.first + 1})
    return found


def find_gaps(labels: np.ndarray, seqs: np.ndarray) -> list[dict[str, Any]]:
    """Runs of unlabelled ('') frames: first/last frame, length and where they are."""
    empty = labels == ""
    gaps = []
    for lo, hi in _runs(empty):
        where = ("before the first segment" if lo == 0 and not empty.all() else
                 "after the last segment" if hi == len(labels) else "between segments")
        gaps.append({"first": int(seqs[lo]), "last": int(seqs[hi - 1]), "frames": hi - lo, "where": where})
    return gaps


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[lo, hi)`` row ranges where ``mask`` (N,) bool is True."""
    padded = np.concatenate(([False], mask, [False])).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def segments_from_labels(labels: np.ndarray, seqs: np.ndarray, source: str = "") -> list[FrameSegment]:
    """Maximal runs of one non-empty label over consecutive rows -> segments (unlabelled rows split runs)."""
    labels = np.asarray(labels, dtype=object)
    if len(labels) == 0:
        return []
    change = np.flatnonzero(labels[1:] != labels[:-1]) + 1
    starts = np.concatenate(([0], change))
    stops = np.concatenate((change, [len(labels)]))
    runs = [(a, b) for a, b in zip(starts, stops) if labels[a] != ""]
    return [FrameSegment(str(labels[a]), int(seqs[a]), int(seqs[b - 1]), f"{source}#{k}")
            for k, (a, b) in enumerate(runs, start=1)]
