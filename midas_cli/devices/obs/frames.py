"""Frame times of a constant-frame-rate OBS recording, and the check of the finished file.

OBS encodes at a fixed rate (GetVideoSettings ``fpsNumerator/fpsDenominator``). Frame i of a file is
at recording time i / fps (``t_device_s``) and at host time ``started_ns + i / fps``, where
``started_ns`` is the host time of the RecordStateChanged STARTED event (DESIGN.md section 4). While
recording, the number of frames OBS has handed to the muxer comes from GetRecordStatus
(``outputDuration`` = frames x frame interval, truncated to ms); at stop the file itself is the truth:
ffprobe lists its video packets, one per encoded frame, with their presentation times.
"""

from __future__ import annotations

import shutil
import subprocess
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.errors import DeviceError

FFPROBE_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class FrameClock:
    """Frame index -> times for one file. ``fps`` exact (e.g. 30000/1001), ``started_ns`` host clock."""

    fps: Fraction
    started_ns: int

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

    def rows(self, first: int, stop: int, seq_base: int = 0) -> list[tuple[int, int, float]]:
        """Stream rows (seq, t_host_ns, t_device_s) of frames ``first .. stop-1`` of this file."""
        return [(seq_base + i, self.host_ns(i), self.time_s(i)) for i in range(first, stop)]


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


def count_existing_frames(files: list[Path]) -> int:
    """Frames in earlier, finished recordings of this session (their rows came first)."""
    return sum(len(probe_frame_times(path)) for path in files)


@dataclass
class RecordingCheck:
    """What the stop-time check found for one file; ``problems`` break one-row-per-frame timing."""

    frames_in_file: int
    rows_live: int
    rows_at_stop: int
    max_time_error_ms: float
    frames_off_grid: int
    first_off_grid: int | None
    obs_counters: dict[str, int]
    problems: list[str]
    warnings: list[str]

    def to_manifest(self) -> dict[str, Any]:
        return {"status": "mismatch" if self.problems else "ok", **self.__dict__}


def check_recording(frame_times_s: np.ndarray, fps: Fraction, rows_live: int,
                    obs_counters: dict[str, int]) -> RecordingCheck:
    """Compare the file's frames with the rows written live and with the constant-rate frame grid.

    ``rows_live`` rows (file frames 0 .. rows_live-1) were written while recording; the rest of the
    file's frames get their rows at stop. ``obs_counters``: OBS's skipped/lagged frame counters
    during the recording (warnings: lagged renders repeat a frame, skipped output frames leave a hole
    that the grid check then finds)."""
    n = len(frame_times_s)
    grid = np.arange(n) / float(fps)
    error_s = np.abs(frame_times_s - grid) if n else np.zeros(0)
    off = np.flatnonzero(~(error_s <= 0.5 / float(fps)))  # NaN (no pts) counts as off the grid
    problems, warnings = [], []
    if rows_live > n:
        problems.append(f"{rows_live - n} row(s) were written live for frames the file does not contain "
                        f"(the file has {n} frames, rows cover frames 0..{rows_live - 1})")
    if len(off):
        problems.append(f"{len(off)} frame(s) are more than half a frame away from i/fps, the first at frame "
                        f"{off[0]}: OBS dropped or repeated frames, so t_host_ns is off after that frame")
    for name, count in obs_counters.items():
        if count:
            warnings.append(f"OBS counted {count} {name.replace('_', ' ')} during the recording")
    return RecordingCheck(n, rows_live, max(0, n - rows_live),
                          round(float(np.nanmax(error_s)) * 1e3, 3) if n else 0.0, len(off),
                          int(off[0]) if len(off) else None, obs_counters, problems, warnings)
