"""Frame times of a constant-frame-rate OBS recording, and the check of the finished file.

OBS encodes at a fixed rate (GetVideoSettings ``fpsNumerator/fpsDenominator``). Frame i of a file is
at recording time i / fps (``t_device_s``) and at host time ``started_ns + i / fps``, where
``started_ns`` is the host time of the RecordStateChanged STARTED event (DESIGN.md section 4). While
recording, the number of frames OBS has handed to the muxer comes from GetRecordStatus
(``outputDuration`` = frames x frame interval, truncated to ms); at stop the file itself is the truth:
ffprobe lists its video packets, one per encoded frame, with their presentation times.

A session's video is one or more files, *segments* (a new one each time midas reconnects to OBS, e.g.
after OBS was restarted): rows carry their segment, and ``seq`` keeps growing across segments on the
frame grid of the session's first frame, so the frames an outage cost show as a gap of their number.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from midas_cli.errors import DeviceError

FFPROBE_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class FrameClock:
    """Frame index -> times for one file (segment). ``fps`` exact (e.g. 30000/1001), ``started_ns`` host
    clock; frame i of the file has ``seq`` = ``seq_base`` + i and is in segment ``segment``."""

    fps: Fraction
    started_ns: int
    seq_base: int = 0
    segment: int = 0

    def time_s(self, index: int) -> float:
        """Recording time of frame ``index`` (s since the file's first frame)."""
        return float(index / self.fps)

    def host_ns(self, index: int) -> int:
        """Host time (Unix-epoch ns) of frame ``index``: STARTED + index / fps."""
        return self.started_ns + round(index * 10**9 / self.fps)

    def frames_in(self, duration_ms: int) -> int:
        """Frames behind an ``outputDuration`` of ``duration_ms``: OBS truncates frames x interval to
        whole ms, which is off by less than 0.1 frame at up to 100 fps, so rounding recovers the count."""
        return round(Fraction(duration_ms, 1000) * self.fps)

    def rows(self, first: int, stop: int) -> list[tuple[int, int, float, int]]:
        """Stream rows (seq, t_host_ns, t_device_s, segment) of frames ``first .. stop-1`` of this file."""
        return [(self.seq_base + i, self.host_ns(i), self.time_s(i), self.segment) for i in range(first, stop)]


@dataclass(frozen=True)
class SegmentRows:
    """The rows a stream file holds for one segment: how many, and its first and last row."""

    rows: int
    first_seq: int
    first_frame: int  # frame index in the file of the first row (0 unless its first rows were lost)
    first_t_host_ns: int
    last_seq: int

    def seq_base(self) -> int:
        """seq of the segment's frame 0."""
        return self.first_seq - self.first_frame

    def started_ns(self, fps: Fraction) -> int:
        """Host time of the segment's frame 0 (its STARTED event)."""
        return self.first_t_host_ns - round(self.first_frame * 10**9 / fps)


@dataclass(frozen=True)
class WrittenRows:
    """What the video stream file already holds, per segment (read back when a segment starts or ends)."""

    segments: dict[int, SegmentRows]
    last_seq: int | None = None
    origin_ns: int | None = None  # host time of seq 0 on the session's frame grid

    @classmethod
    def read(cls, path: Path, fps: Fraction) -> "WrittenRows":
        """Read ``path`` (a video stream CSV: seq, t_host_ns, t_device_s, segment); an absent or empty
        file holds no rows."""
        try:
            table = pd.read_csv(path, usecols=["seq", "t_host_ns", "t_device_s", "segment"],
                                dtype={"seq": "int64", "t_host_ns": "int64", "t_device_s": "float64",
                                       "segment": "int64"})
        except FileNotFoundError:
            return cls({})
        if table.empty:
            return cls({})
        seq, t_host = table["seq"].to_numpy(), table["t_host_ns"].to_numpy()  # int64: no float round trip
        t_device, segment = table["t_device_s"].to_numpy(), table["segment"].to_numpy()
        starts = np.flatnonzero(np.r_[True, segment[1:] != segment[:-1]])
        ends = np.r_[starts[1:], len(segment)]
        segments = {}
        for start, end in zip(starts, ends):
            segments[int(segment[start])] = SegmentRows(int(end - start), int(seq[start]),
                                                        round(float(t_device[start]) * fps), int(t_host[start]),
                                                        int(seq[end - 1]))
        origin = int(t_host[0]) - round(int(seq[0]) * 10**9 / fps)
        return cls(segments, int(seq[-1]), origin)

    def next_segment(self, files: dict[int, Path]) -> int:
        """The index of a new segment: after every segment with rows or with a file."""
        known = set(self.segments) | set(files)
        return max(known) + 1 if known else 0

    def seq_base(self, fps: Fraction, started_ns: int) -> int:
        """seq of frame 0 of a segment that started at host time ``started_ns``: on the frame grid of the
        session's first frame (so the frames the outage cost leave a gap of their number), and after every
        seq already written (seq only grows)."""
        if self.last_seq is None:
            return 0
        grid = round(Fraction(started_ns - self.origin_ns, 10**9) * fps)
        return max(grid, self.last_seq + 1)


def segment_files(folder: Path, device: str) -> dict[int, Path]:
    """The session's recording files of ``device``: segment -> ``<device>_s<segment>_<date>_<time>.mkv``."""
    pattern = re.compile(rf"^{re.escape(device)}_s(\d+)_.*\.mkv$")
    files: dict[int, Path] = {}
    for path in sorted(folder.glob(f"{device}_s*.mkv")):
        match = pattern.match(path.name)
        if match:
            files.setdefault(int(match.group(1)), path)
    return files


def probe_frame_times(path: Path) -> np.ndarray:
    """Presentation times (s, ascending, shape (frames,)) of the first video stream's packets."""
    if shutil.which("ffprobe") is None:
        raise DeviceError("ffprobe was not found: install ffmpeg (apt-get install ffmpeg) to check OBS recordings")
    command = ["ffprobe", "-v", "error", "-select_streams", "v:0", "-show_entries", "packet=pts_time",
               "-of", "csv=p=0", str(path)]
    try:
        result = subprocess.run(command, capture_output=True, text=True, timeout=FFPROBE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise DeviceError(f"ffprobe took more than {FFPROBE_TIMEOUT_S:.0f} s on {path}") from None
    if result.returncode != 0:
        raise DeviceError(f"ffprobe could not read {path}: {result.stderr.strip()[-300:]}")
    times = [float(line) if line.strip() not in ("", "N/A") else np.nan for line in result.stdout.splitlines()]
    return np.sort(np.asarray(times, dtype=float))


@dataclass
class RecordingCheck:
    """What the stop-time check found for one file (segment); ``problems`` break one-row-per-frame
    timing. ``rows_without_frame``: rows written live for frames the file does not hold (an OBS that
    was killed never wrote them); ``frames_without_row``: frames an earlier segment's file holds after
    its last row (written after midas's last poll; missing rows, counted in the outage that followed)."""

    frames_in_file: int
    rows_live: int
    rows_at_stop: int
    rows_without_frame: int
    frames_without_row: int
    max_time_error_ms: float
    frames_off_grid: int
    first_off_grid: int | None
    obs_counters: dict[str, int] | None
    problems: list[str]
    warnings: list[str]

    def to_manifest(self) -> dict[str, Any]:
        return {"status": "mismatch" if self.problems else "ok", **self.__dict__}


def check_recording(frame_times_s: np.ndarray, fps: Fraction, rows_live: int,
                    obs_counters: dict[str, int] | None, final: bool = True,
                    seq_base: int | None = None) -> RecordingCheck:
    """Compare a file's frames with the rows written live and with the constant-rate frame grid.

    ``rows_live`` rows (file frames 0 .. rows_live-1) were written while recording; in the ``final``
    segment the rest of the file's frames get their rows at stop, in an earlier one they have none.
    ``obs_counters``: OBS's skipped/lagged frame counters during the recording, None if unknown
    (warnings: lagged renders repeat a frame, skipped output frames leave a hole that the grid check
    then finds). ``seq_base``: seq of the file's frame 0, to name the rows concerned."""
    n = len(frame_times_s)
    grid = np.arange(n) / float(fps)
    error_s = np.abs(frame_times_s - grid) if n else np.zeros(0)
    off = np.flatnonzero(~(error_s <= 0.5 / float(fps)))  # NaN (no pts) counts as off the grid
    problems, warnings = [], []
    without_frame = max(0, rows_live - n)
    without_row = 0 if final else max(0, n - rows_live)
    if without_frame:
        rows = "" if seq_base is None else f", seq {seq_base + n}..{seq_base + rows_live - 1}"
        problems.append(f"{without_frame} row(s) were written live for frames the file does not contain (the file "
                        f"has {n} frames, rows cover frames 0..{rows_live - 1}{rows})"
                        + ("" if final else ": OBS ended without writing them (killed?); the rows stay in the "
                                            "stream, these frames are not in any video file"))
    if without_row:
        warnings.append(f"the file's last {without_row} frame(s) have no row (OBS wrote them after midas's last "
                        f"poll of this recording): they are in the seq gap of the outage that followed")
    if len(off):
        problems.append(f"{len(off)} frame(s) are more than half a frame away from i/fps, the first at frame "
                        f"{off[0]}: OBS dropped or repeated frames, so t_host_ns is off after that frame")
    for name, count in (obs_counters or {}).items():
        if count:
            warnings.append(f"OBS counted {count} {name.replace('_', ' ')} during the recording")
    return RecordingCheck(n, rows_live, max(0, n - rows_live) if final else 0, without_frame, without_row,
                          round(float(np.nanmax(error_s)) * 1e3, 3) if n else 0.0, len(off),
                          int(off[0]) if len(off) else None, obs_counters, problems, warnings)


def unreadable_recording(rows_live: int, reason: str) -> RecordingCheck:
    """The check of a segment whose file is missing or cannot be read: every row lacks its frame."""
    return RecordingCheck(0, rows_live, 0, rows_live, 0, 0.0, 0, None, None,
                          [f"{reason}: its {rows_live} row(s) have no frame that midas could check"], [])
