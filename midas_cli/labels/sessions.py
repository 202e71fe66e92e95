"""Label sets in sessions: import annotations onto the session's video frames, export them, gather
recordings for statistics. Session folders are touched only through ``midas_cli.session``.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from midas_cli.errors import ConfigError, SessionError
from midas_cli.labels.segments import (FrameClock, FrameSegment, RasterReport, TimedSegment, rasterize,
                                      segments_from_labels)
from midas_cli.labels.stats import Recording, natural_key
from midas_cli.labels.taxonomy import Taxonomy, load_taxonomy, shipped_taxonomy
from midas_cli.labels.transcription import JIGSAWS_FPS, read_transcription, transcription_files
from midas_cli.labels.via import annotators, read_via, via_csv_text, via_project, via_segments
from midas_cli.session.labels import list_label_sets, read_frame_labels, write_frame_labels
from midas_cli.session.manifest import MANIFEST_NAME
from midas_cli.session.reader import Session

log = logging.getLogger(__name__)

VIDEO_STREAM = "video"
FRAME_RULE = "frame i covers [i/fps, (i+1)/fps); labelled when its midpoint (i+0.5)/fps is in [start, end)"
EXPORT_FORMATS = ("via", "via-csv", "csv")


@dataclass(frozen=True)
class ImportOptions:
    """How segments become frame labels, and where they go."""

    taxonomy: str
    gaps: str = "unlabelled"
    overlap: str = "later"
    name: str = "gestures"
    force: bool = False


@dataclass
class ImportResult:
    path: Path
    meta: dict[str, Any]
    report: RasterReport

    def to_json(self) -> dict[str, Any]:
        return {"labels": str(self.path), **self.meta}


def video_clock(session: Session, stream: str = VIDEO_STREAM) -> FrameClock:
    """The session's video frames (``seq``) and rate; the ``t_device_s`` timecode, when recorded, must
    agree with ``seq / fps`` within half a frame (a constant-frame-rate recording)."""
    frame = session.read_stream(stream)
    fps = session.stream_spec(stream).nominal_rate_hz
    seqs = frame["seq"].to_numpy(dtype=np.int64)
    if len(seqs) > 1 and not (np.diff(seqs) > 0).all():
        raise SessionError(f"{session.path}: video frame indices (seq) are not strictly increasing")
    if "t_device_s" in frame and len(seqs):
        error = np.abs(frame["t_device_s"].to_numpy(dtype=float) - seqs / fps)
        if np.nanmax(error) > 0.5 / fps:
            worst = int(np.nanargmax(error))
            raise SessionError(f"{session.path}: video frame {seqs[worst]} has timecode "
                               f"{frame['t_device_s'].iloc[worst]:.6f} s, expected {seqs[worst] / fps:.6f} s at "
                               f"{fps:g} fps; labels need a constant-frame-rate recording")
    return FrameClock(seqs, fps)


def import_via(export: Path, session_path: Path, options: ImportOptions, attribute: str | None = None,
               video_file: str | None = None, annotator: str | None = None) -> ImportResult:
    """VIA 3 project JSON or CSV export -> label set ``options.name`` of the session."""
    taxonomy = load_taxonomy(options.taxonomy)
    session, clock = _open_for_write(session_path, options)
    project = read_via(Path(export))
    timed, skipped = via_segments(project, taxonomy, attribute, video_file)
    if not timed:
        raise SessionError(f"{export} holds no gesture segments ({len(skipped)} entries skipped: "
                           f"{'; '.join(sorted({s['reason'] for s in skipped})) or 'none'})")
    frames = []
    for seg in timed:
        converted = clock.to_frames(seg)
        if converted is None:
            skipped.append({"segment": seg.source, "z": [seg.start_s, seg.end_s], "reason": "covers no frame midpoint"})
        else:
            frames.append(converted)
    names = [annotator] if annotator else annotators(project)
    source = {"kind": project.kind, **_file_facts(Path(export)), "annotator": ", ".join(names) or None}
    return _write(session, clock, frames, taxonomy, options, source, skipped)


def import_transcription(path: Path, session_path: Path, options: ImportOptions,
                         index_base: int = 1) -> ImportResult:
    """A JIGSAWS/COMPASS transcription (frame numbers from ``index_base``) -> label set of the session."""
    taxonomy = load_taxonomy(options.taxonomy)
    session, clock = _open_for_write(session_path, options)
    segments = read_transcription(Path(path), index_base)
    for seg in segments:
        taxonomy.gesture(seg.label)
    source = {"kind": "transcription", **_file_facts(Path(path)), "annotator": None, "index_base": index_base}
    return _write(session, clock, segments, taxonomy, options, source, [])


def _open_for_write(session_path: Path, options: ImportOptions) -> tuple[Session, FrameClock]:
    session = Session.open(session_path)
    if options.name in list_label_sets(session.path) and not options.force:
        raise SessionError(f"{session.path} already has label set {options.name!r}; pass --force to replace it "
                           "or --name to keep both")
    return session, video_clock(session)


def _write(session: Session, clock: FrameClock, segments: Sequence[FrameSegment], taxonomy: Taxonomy,
           options: ImportOptions, source: dict[str, Any], skipped: list[dict[str, Any]]) -> ImportResult:
    labels, report = rasterize(segments, clock.seqs, options.overlap, options.gaps, taxonomy.idle)
    report.skipped = skipped
    meta = {"taxonomy": taxonomy.name, "source": source, "fps": clock.fps, "frame_rule": FRAME_RULE,
            "report": report.to_json()}
    path = write_frame_labels(session.path, clock.seqs, labels, meta, options.name)
    log.info("wrote %s: %d frames from %d segments", path, len(labels), len(segments))
    return ImportResult(path, meta, report)


def _file_facts(path: Path) -> dict[str, str]:
    try:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as exc:
        raise SessionError(f"cannot read {path}: {exc.strerror}") from exc
    return {"file": str(path.resolve()), "sha256": digest}


def session_segments(session_path: Path, name: str = "gestures") -> tuple[list[FrameSegment], FrameClock, dict]:
    """The label set as segments (runs of one label), the video clock and the label set's meta."""
    session = Session.open(session_path)
    clock = video_clock(session)
    labels = read_frame_labels(session.path, name)
    segments = segments_from_labels(labels.labels, labels.frames, session.path.name)
    return segments, clock, labels.meta


def export_labels(session_path: Path, fmt: str, name: str = "gestures") -> str:
    """Text of the label set as a VIA 3 project JSON (``via``), VIA 3 CSV export (``via-csv``) or a plain
    CSV of segments (``csv``: gesture, frames inclusive, seconds ``[start, end)``)."""
    if fmt not in EXPORT_FORMATS:
        raise SessionError(f"export format must be one of {', '.join(EXPORT_FORMATS)}, got {fmt!r}")
    segments, clock, meta = session_segments(session_path, name)
    if fmt == "csv":
        return _segments_csv(segments, clock)
    ids = _gesture_ids(segments, meta)
    session_id = Path(session_path).resolve().name
    timed = [_timed(s, clock) for s in segments]
    project = via_project(timed, ids, f"{session_id}.mkv", session_id, f"gesture ({meta.get('taxonomy', 'labels')})")
    return json.dumps(project, indent=1) + "\n" if fmt == "via" else via_csv_text(project)


def _timed(seg: FrameSegment, clock: FrameClock) -> TimedSegment:
    start, end = clock.seconds(seg.first, seg.last)
    return TimedSegment(seg.label, start, end, seg.source)


def _gesture_ids(segments: Sequence[FrameSegment], meta: dict[str, Any]) -> list[str]:
    used = sorted({s.label for s in segments}, key=natural_key)
    try:
        ids = shipped_taxonomy(str(meta.get("taxonomy"))).ids
    except ConfigError:  # no or unknown taxonomy recorded: the labels themselves are the options
        return used
    return ids + [u for u in used if u not in ids]


def _segments_csv(segments: Sequence[FrameSegment], clock: FrameClock) -> str:
    lines = ["gesture,start_frame,end_frame,frames,start_s,end_s,duration_s"]
    for s in segments:
        start, end = clock.seconds(s.first, s.last)
        lines.append(f"{s.label},{s.first},{s.last},{s.frames},{start:.5f},{end:.5f},{end - start:.5f}")
    return "\n".join(lines) + "\n"


def load_recordings(paths: Sequence[Path], name: str = "gestures",
                    fps: float = JIGSAWS_FPS) -> tuple[list[Recording], str | None]:
    """Sessions (their label set ``name``) and transcription files/folders -> recordings, plus the
    taxonomy named by the sessions' label sets when they agree on one."""
    recordings, taxonomies = [], set()
    for path in paths:
        path = Path(path)
        if (path / MANIFEST_NAME).is_file():
            segments, clock, meta = session_segments(path, name)
            recordings.append(Recording(path.name, tuple(segments), clock.fps))
            taxonomies.add(meta.get("taxonomy") if isinstance(meta.get("taxonomy"), str) else None)
        else:
            for file in transcription_files(path):
                recordings.append(Recording(file.name, tuple(read_transcription(file)), fps))
    known = taxonomies - {None}
    return recordings, (known.pop() if len(known) == 1 else None)
