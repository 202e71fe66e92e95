"""JIGSAWS / COMPASS gesture transcriptions: one ``start end Gk`` line per segment.

Frames are numbered from 1 (the first video frame / first kinematics line is frame 1; the 34 COMPASS
suturing files never use frame 0), the end frame is inclusive, the rate is 30 Hz, lines end in CRLF
and may carry trailing spaces. ``index_base`` turns those numbers into midas' 0-based frame indices:
frame ``k`` of a transcription is video frame ``k - index_base``.
"""

from __future__ import annotations

from pathlib import Path

from midas_cli.errors import SessionError
from midas_cli.labels.segments import FrameSegment

JIGSAWS_FPS = 30.0
JIGSAWS_INDEX_BASE = 1


def read_transcription(path: Path, index_base: int = JIGSAWS_INDEX_BASE) -> list[FrameSegment]:
    """Segments of one transcription file as 0-based inclusive frame ranges, in file order."""
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise SessionError(f"cannot read transcription {path}: {exc}") from exc
    segments = []
    for number, line in enumerate(lines, start=1):
        if line.strip():
            segments.append(_parse_line(line, index_base, f"{Path(path).name}:{number}"))
    if not segments:
        raise SessionError(f"transcription {path} has no segments (expected 'start end Gk' lines)")
    return segments


def _parse_line(line: str, index_base: int, where: str) -> FrameSegment:
    parts = line.split()
    if len(parts) != 3:
        raise SessionError(f"{where}: expected 'start end gesture', got {line.strip()!r}")
    try:
        start, end = int(parts[0]), int(parts[1])
    except ValueError:
        raise SessionError(f"{where}: start/end must be whole frame numbers, got {line.strip()!r}") from None
    if end < start or start < index_base:
        raise SessionError(f"{where}: frames {start}..{end} are not an ascending range from {index_base}")
    return FrameSegment(parts[2], start - index_base, end - index_base, where)


def transcription_files(path: Path) -> list[Path]:
    """``path`` itself, or the ``*.txt`` files of a folder (sorted); error when none."""
    path = Path(path)
    files = sorted(path.glob("*.txt")) if path.is_dir() else [path]
    if not files or not files[0].is_file():
        raise SessionError(f"{path}: no transcription files (a 'start end Gk' .txt file or a folder of them)")
    return files
