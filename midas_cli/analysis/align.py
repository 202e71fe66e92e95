"""Every stream of a session onto the video frame clock (DESIGN.md section 7), plus a lag estimator.

Reference clock: the ``t_host_ns`` of the ``video`` stream (frame i = video ``seq`` i). Each other
stream is associated with each frame causally (latest sample at or before the frame time) or by the
nearest sample; ``<stream>_delta_ms`` = chosen sample time - frame time (host clock, ms). A frame whose
chosen sample is further than ``stale_periods`` nominal sample periods away (before the stream starts,
after it ends, inside an outage) is masked, never filled with a sentinel value.

Column names in the aligned table: ``<stream>.<column>`` for raw values, and derived columns:
``emht.{left,right}_hand_{x,y,z}_mm`` (midpoint of the hand's thumb and middle sensors, transmitter
frame), ``emht.{hand}_grasper_mm`` (thumb-middle sensor distance), ``emht.{hand}_v{x,y,z}_mm_s``
(velocity of the hand point), ``handkp.{hand}_hand_{x,y,z}_mm`` (keypoint midpoint, camera frame,
gap-filled), ``handkp.{hand}_filled`` (0 detected, 1 spline-filled, 2 forward-filled), ``clutch``
(0/1), and ``<source>_<target>_<model>.{hand}_{x,y,z}_mm`` / ``_{yaw,pitch,roll}_deg`` where a
calibration in ``calib/`` maps a source (emht, handkp) into a robot frame (mtm, psm).
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
import hashlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
from scipy.interpolate import CubicSpline

from midas_cli.analysis.calibration import MODEL_CHOICES, SOURCES, TARGETS, Calibration, load_calibration
from midas_cli.errors import ConfigError, SessionError
from midas_cli.geometry import angles_from_matrices, matrices_from_angles, matrices_from_quaternions
from midas_cli.session.derived import AlignedTable, ValuesFile, find_calibration, write_aligned
from midas_cli.session.outputs import provenance, session_lock
from midas_cli.session.reader import Session
from midas_cli.session.values import FLOAT_LIMIT, REMEDY

log = logging.getLogger(__name__)

METHODS = ("causal", "nearest")
HANDS = ("left", "right")
EMHT_SENSORS = {"left": (2, 1), "right": (3, 4)}  # (thumb, middle) trakSTAR sensor numbers
CLUTCH_FPS_CHANNEL = 5  # the paper's "Pedal 5 = Clutch"
REFERENCE = "video"


@dataclass(frozen=True)
class AlignOptions:
    """``method`` causal|nearest; ``rate_hz`` downsamples the frame clock (None keeps every frame);
    gaps in HandKP up to ``spline_max_gap_s`` are spline-filled, longer ones forward-filled;
    ``clock_hz`` None aligns onto the video frame clock, a rate (Hz) onto a regular clock at that rate
    spanning every stream's samples (for a short or missing video clock). ``model`` best|rigid|mlp: the
    calibration model recorded as the one to use (``calibrations_applied[].selected``; both models'
    columns are written either way): best = the winner of calibrate's held-out comparison."""

    method: str = "causal"
    rate_hz: float | None = None
    spline_max_gap_s: float = 1.0
    stale_periods: float = 3.0
    clock_hz: float | None = None
    model: str = "best"

    def __post_init__(self) -> None:
        if self.model not in MODEL_CHOICES:
            raise ConfigError(f"--model {self.model!r} is unknown (expected one of {', '.join(MODEL_CHOICES)})")
        if self.method not in METHODS:
            raise ConfigError(f"alignment method {self.method!r} is unknown (expected one of {', '.join(METHODS)})")
        if self.rate_hz is not None and not 0 < self.rate_hz <= 1000:
            raise ConfigError(f"--rate must be in (0, 1000] Hz, got {self.rate_hz}")
        if self.clock_hz is not None and not 0 < self.clock_hz <= 1000:
            raise ConfigError(f"--clock must be 'video' or a rate in (0, 1000] Hz, got {self.clock_hz}")


def parse_clock(text: str) -> float | None:
    """``--clock`` value: 'video' -> None (the video frame clock), a number -> that rate in Hz."""
    if text.strip().lower() == REFERENCE:
        return None
    try:
        return float(text)
    except ValueError:
        raise ConfigError(f"--clock must be 'video' or a rate in Hz such as 30, got {text!r}") from None


class ColumnSet:
    """Aligned columns being built: name -> (N,) float64 values (NaN = masked) and metadata.

    The columns live side by side in one column-major block, so the finished table is a view of it
    (no copy of the whole table) and raw streams are gathered straight into their columns."""

    def __init__(self, n_frames: int, capacity: int = 128) -> None:
        self.n = n_frames
        self._block = np.empty((n_frames, capacity), order="F")
        self._index: dict[str, int] = {}
        self.meta: dict[str, dict[str, Any]] = {}

    @property
    def names(self) -> list[str]:
        return list(self._index)

    def claim(self, names: list[str]) -> np.ndarray:
        """(len(names), N) storage for new columns ``names`` (row j = column j), to be filled in place;
        their metadata is set with ``describe``."""
        used = len(self._index)
        if used + len(names) > self._block.shape[1]:
            grown = np.empty((self.n, max(2 * self._block.shape[1], used + len(names))), order="F")
            grown[:, :used] = self._block[:, :used]
            self._block = grown
        for k, name in enumerate(names):
            if name in self._index:
                raise SessionError(f"aligned column {name!r} computed twice")
            self._index[name] = used + k
        return self._block[:, used : used + len(names)].T

    def describe(self, name: str, unit: str = "", source: str = "", **meta: Any) -> None:
        self.meta[name] = {"unit": unit, "source": source, **{k: v for k, v in meta.items() if v}}

    def add(self, name: str, values: np.ndarray, unit: str = "", source: str = "", **meta: Any) -> None:
        values = np.asarray(values, dtype=float)
        if values.shape != (self.n,):
            raise SessionError(f"aligned column {name!r} has shape {values.shape}, expected ({self.n},)")
        self.claim([name])[0] = values  # a name added twice is an error: written columns never change
        self.describe(name, unit, source, **meta)

    def get(self, name: str) -> np.ndarray | None:
        index = self._index.get(name)
        return None if index is None else self._block[:, index]

    def stack(self, names: list[str]) -> np.ndarray:
        """(N, len(names)) of existing columns."""
        return np.column_stack([self.get(n) for n in names])

    def table(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows), C) column-major: a view of the block when every frame is kept."""
        values = self._block[:, : len(self._index)]
        return values if len(rows) == self.n else np.asfortranarray(values[rows])


class StagedColumns:
    """Columns computed against a ColumnSet without changing it, added later with ``commit``: lets
    independent feature groups run on separate threads and still land in a fixed column order."""

    def __init__(self, columns: ColumnSet) -> None:
        self.columns, self.n = columns, columns.n
        self.staged: list[tuple[str, np.ndarray, str, str, dict[str, Any]]] = []

    def get(self, name: str) -> np.ndarray | None:
        return self.columns.get(name)

    def stack(self, names: list[str]) -> np.ndarray:
        return self.columns.stack(names)

    def add(self, name: str, values: np.ndarray, unit: str = "", source: str = "", **meta: Any) -> None:
        self.staged.append((name, values, unit, source, meta))

    def commit(self) -> None:
        for name, values, unit, source, meta in self.staged:
            self.columns.add(name, values, unit, source, **meta)


def in_parallel(columns: ColumnSet, groups: list[Callable[[Any], None]]) -> None:
    """Run feature groups (each ``group(columns_like)``) on threads, then add their columns in order."""
    staged = [StagedColumns(columns) for _ in groups]
    with ThreadPoolExecutor(max_workers=max(1, min(len(groups), os.cpu_count() or 1))) as pool:
        list(pool.map(lambda pair: pair[0](pair[1]), zip(groups, staged)))
    for group in staged:
        group.commit()


def associate(sample_ns: np.ndarray, frame_ns: np.ndarray, method: str, stale_ns: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index of the sample chosen for each frame, its validity and its offset.

    sample_ns (M,) ascending, frame_ns (N,) host ns. Returns idx (N,) int (clipped into range),
    valid (N,) bool, delta_ms (N,) float = sample time - frame time (NaN where invalid).
    """
    if len(sample_ns) == 0:
        return np.zeros(len(frame_ns), dtype=int), np.zeros(len(frame_ns), bool), np.full(len(frame_ns), np.nan)
    after = np.searchsorted(sample_ns, frame_ns, side="right")
    idx = after - 1  # latest sample at or before the frame
    if method == "nearest":
        nxt = np.minimum(after, len(sample_ns) - 1)
        prev = np.maximum(idx, 0)
        take_next = (idx < 0) | (np.abs(sample_ns[nxt] - frame_ns) < np.abs(frame_ns - sample_ns[prev]))
        idx = np.where(take_next, nxt, prev)
    valid = idx >= 0
    idx = np.clip(idx, 0, len(sample_ns) - 1)
    offset = sample_ns[idx] - frame_ns
    valid &= np.abs(offset) <= stale_ns
    return idx, valid, np.where(valid, offset / 1e6, np.nan)


def coverage(sample_ns: np.ndarray, frame_ns: np.ndarray) -> dict[str, Any]:
    """How much of a stream the frame clock covers: of its samples (sample_ns (M,) ascending, host ns)
    the count and share inside [first frame, last frame], and the share of its time span (first to
    last sample) inside that interval (1.0 for a single sample inside)."""
    if len(sample_ns) == 0 or len(frame_ns) == 0:
        return {"samples": int(len(sample_ns)), "samples_inside": 0, "samples_share": 0.0, "span_s": 0.0,
                "span_share": 0.0}
    first, last = int(frame_ns[0]), int(frame_ns[-1])
    inside = int(np.searchsorted(sample_ns, last, side="right") - np.searchsorted(sample_ns, first, side="left"))
    span = int(sample_ns[-1] - sample_ns[0])
    overlap = max(0, min(last, int(sample_ns[-1])) - max(first, int(sample_ns[0])))
    span_share = overlap / span if span > 0 else float(inside > 0)
    return {"samples": int(len(sample_ns)), "samples_inside": inside,
            "samples_share": round(inside / len(sample_ns), 4), "span_s": round(span / 1e9, 3),
            "span_share": round(span_share, 4)}


def associate_stream(table: np.ndarray, spec_columns: list[str], frame_ns: np.ndarray, method: str,
                     stale_ns: int, out: np.ndarray | None = None, covered: dict[str, Any] | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Values of ``spec_columns`` of a stream (structured array, see ``Session.read_columns``) at each
    frame, NaN where masked, as ``out`` (C, N) (row j = column j; allocated if None), and delta_ms (N,).
    Only the chosen rows are read, so a memory-mapped stream is never copied whole. ``covered``, if
    given, receives the stream's ``coverage`` by the frames."""
    sample_ns = np.ascontiguousarray(table["t_host_ns"], dtype=np.int64)  # one strided pass over the rows
    order = None
    if len(sample_ns) > 1 and (np.diff(sample_ns) < 0).any():
        order = np.argsort(sample_ns, kind="stable")
        sample_ns = sample_ns[order]
    if covered is not None:
        covered.update(coverage(sample_ns, frame_ns))
    idx, valid, delta = associate(sample_ns, frame_ns, method, stale_ns)
    values = np.empty((len(spec_columns), len(frame_ns))) if out is None else out
    if len(sample_ns):
        chosen = table.view(np.ndarray)[idx if order is None else order[idx]]  # whole rows, one pass
        for j, name in enumerate(spec_columns):
            values[j] = chosen[name]
        if not valid.all():
            values[:, ~valid] = np.nan
    else:
        values[:] = np.nan
    return values, delta


def value_columns(session: Session, stream: str) -> list[Any]:
    """The data columns of a stream: everything except seq, t_host_ns and device-clock columns."""
    return [c for c in session.stream_spec(stream).columns if c.clock is None and c.name != "seq"]


def stale_ns_for(session: Session, stream: str, options: AlignOptions) -> int:
    rate = session.stream_spec(stream).nominal_rate_hz  # None: an event stream
    return int(options.stale_periods * 1e9 / rate) if rate else int(1e9)


def refuse_absurd_values(session: Session, stream: str, table: np.ndarray, columns: list[Any],
                         chosen: np.ndarray) -> None:
    """SessionError naming file and line if a float value chosen for a frame (``chosen`` (C, N), row j =
    ``columns[j]``) is infinite or beyond ``FLOAT_LIMIT`` (a binary copy made before values were checked
    can hold them; the CSV parser refuses them)."""
    for j, column in enumerate(columns):
        if column.dtype != "float" or not (np.abs(chosen[j]) > FLOAT_LIMIT).any():  # inf included, NaN not
            continue
        row = int(np.flatnonzero(np.abs(np.asarray(table[column.name], dtype=float)) > FLOAT_LIMIT)[0])
        raise SessionError(f"{session.stream_path(stream)} line {row + 2}, column {column.name!r}: "
                           f"{float(table[column.name][row]):g} is out of range; expected a finite number within "
                           f"+-{FLOAT_LIMIT:.0e}; {REMEDY}")


def time_order_warnings(session: Session, data: dict[str, np.ndarray]) -> list[str]:
    """One line per stream whose host time goes backwards (rows out of order, or a clock stepped back):
    `align` associates its samples in time order, which the file does not guarantee to be right."""
    lines = []
    for stream, table in data.items():
        t_host = np.asarray(table["t_host_ns"], dtype=np.int64)
        step = np.diff(t_host)
        back = np.flatnonzero(step < 0)
        if len(back):
            first = int(back[0])
            lines.append(f"host time of stream {stream!r} ({session.stream_path(stream)}) goes backwards at "
                         f"{len(back)} row(s), first at line {first + 3} (by {-step[first] / 1e6:.3f} ms); its "
                         f"samples were associated in time order (`midas session verify` reports the file)")
    return lines


def reference_frames(session: Session, video: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Video frame indices (N,) and host times (N,) ns: the reference clock, sorted by time (``video``:
    the video stream as ``Session.read_columns`` gives it, read here if None)."""
    if REFERENCE not in session.stream_names:
        raise SessionError(f"{session.path} has no {REFERENCE!r} stream: it is the frame clock `align` needs "
                           "(--clock RATE aligns onto a regular clock instead, e.g. --clock 30)")
    video = session.read_columns(REFERENCE) if video is None else video
    if len(video) == 0:
        raise SessionError(f"{session.path}: the video stream has no frames")
    order = np.argsort(video["t_host_ns"], kind="stable")
    return np.asarray(video["seq"], np.int64)[order], np.asarray(video["t_host_ns"], np.int64)[order]


def regular_frames(data: dict[str, np.ndarray], rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """A regular clock at ``rate_hz`` from the first sample of any stream in ``data`` to the first tick at
    or after the last one: frame indices (N,) and host times (N,) ns (frame k at first + k / rate)."""
    times = [np.asarray(t["t_host_ns"], dtype=np.int64) for t in data.values() if len(t)]
    if not times:
        raise SessionError("no stream has samples: nothing to span with a regular clock")
    first, last = min(int(t.min()) for t in times), max(int(t.max()) for t in times)
    n = int(np.ceil((last - first) * rate_hz / 1e9 - 1e-9)) + 1
    frames = np.arange(n, dtype=np.int64)
    return frames, first + np.round(frames * 1e9 / rate_hz).astype(np.int64)


def read_streams(session: Session) -> dict[str, np.ndarray]:
    """Every stream except the reference as a structured array (memory-mapped binary copy, or the CSV
    parsed when the session has none)."""
    return {name: session.read_columns(name) for name in session.stream_names if name != REFERENCE}


def add_raw_streams(session: Session, data: dict[str, np.ndarray], columns: ColumnSet, frame_ns: np.ndarray,
                    options: AlignOptions, shifts_ns: dict[str, int],
                    covered: dict[str, dict[str, Any]] | None = None) -> None:
    """Associate every stream in ``data`` with the frames; a stream in ``shifts_ns`` is associated at
    frame time + shift (compensating a known latency). ``covered``, if given, receives each stream's
    ``coverage`` by the frames."""
    cols_of = {stream: value_columns(session, stream) for stream in data}
    names = {stream: [f"{stream}.{c.name}" for c in cols] + [f"{stream}_delta_ms"] for stream, cols in cols_of.items()}
    storage = columns.claim([n for stream_names in names.values() for n in stream_names])  # one claim: no regrowth
    starts = np.cumsum([0, *(len(n) for n in names.values())])
    blocks = {stream: storage[start : start + len(names[stream])] for stream, start in zip(names, starts)}

    if covered is not None:
        covered.update({stream: {} for stream in data})  # filled by the threads, each its own entry

    def one(stream: str) -> None:
        names = [c.name for c in cols_of[stream]]
        found = None if covered is None else covered[stream]
        _, delta = associate_stream(data[stream], names, frame_ns + shifts_ns.get(stream, 0), options.method,
                                    stale_ns_for(session, stream, options), out=blocks[stream][:-1], covered=found)
        blocks[stream][-1] = delta
        refuse_absurd_values(session, stream, data[stream], cols_of[stream], blocks[stream][:-1])

    # numpy's searchsorted and gathers release the GIL: streams are associated on every core
    with ThreadPoolExecutor(max_workers=max(1, min(len(data), os.cpu_count() or 1))) as pool:
        list(pool.map(one, data))
    for stream, cols in cols_of.items():
        for col in cols:
            columns.describe(f"{stream}.{col.name}", col.unit, stream, frame=col.frame, description=col.description)
        columns.describe(f"{stream}_delta_ms", "ms", stream, description="chosen sample time - frame time")


def emht_sensor_arrays(columns: ColumnSet, prefix: str = "emht") -> tuple[np.ndarray, np.ndarray] | None:
    """(N, 4, 3) positions (mm) and (N, 4, 3) yaw/pitch/roll (deg) of sensors 1..4, or None."""
    names = [f"{prefix}.s{s}_{a}_mm" for s in range(1, 5) for a in "xyz"]
    if any(columns.get(n) is None for n in names):
        return None
    angles = [f"{prefix}.s{s}_{a}_deg" for s in range(1, 5) for a in ("azimuth", "elevation", "roll")]
    pos = columns.stack(names).reshape(-1, 4, 3)
    ang = columns.stack(angles).reshape(-1, 4, 3) if all(columns.get(n) is not None for n in angles) else None
    return pos, ang


def hand_points(sensor_pos: np.ndarray) -> dict[str, np.ndarray]:
    """Hand point (N, 3) = midpoint of the thumb and middle sensors, per hand."""
    return {h: (sensor_pos[:, t - 1] + sensor_pos[:, m - 1]) / 2 for h, (t, m) in EMHT_SENSORS.items()}


def add_emht_features(columns: ColumnSet, t_s: np.ndarray) -> None:
    """Hand points, grasper distances and hand velocities from the aligned EmHT sensors."""
    arrays = emht_sensor_arrays(columns)
    if arrays is None:
        return
    pos = arrays[0]
    for hand, point in hand_points(pos).items():
        thumb, middle = EMHT_SENSORS[hand]
        for k, axis in enumerate("xyz"):
            columns.add(f"emht.{hand}_hand_{axis}_mm", point[:, k], "mm", "emht", frame="emht_transmitter",
                        description="midpoint of the thumb and middle sensors")
        columns.add(f"emht.{hand}_grasper_mm", np.linalg.norm(pos[:, thumb - 1] - pos[:, middle - 1], axis=1), "mm",
                    "emht", description="thumb-middle sensor distance (grasper opening)")
        velocity = velocity_mm_s(point, t_s)
        for k, axis in enumerate("xyz"):
            columns.add(f"emht.{hand}_v{axis}_mm_s", velocity[:, k], "mm/s", "emht", frame="emht_transmitter",
                        description="hand point velocity (central differences on the frame clock)")


def velocity_mm_s(points: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """Central-difference velocity (N, 3) of points (N, 3) mm sampled at t_s (N,) s; NaN propagates."""
    if len(t_s) < 2:
        return np.full_like(points, np.nan)
    return np.gradient(points, t_s, axis=0)


def fill_gaps(t_s: np.ndarray, values: np.ndarray, max_spline_gap_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Fill NaN rows of ``values`` (N, D): cubic spline through the valid rows for gaps whose bounding
    valid frames are at most ``max_spline_gap_s`` apart, forward fill otherwise (also after the last
    valid row); rows before the first valid row stay NaN. Returns filled (N, D), fill code (N,) int
    (0 = original, 1 = spline, 2 = forward fill, -1 = still missing)."""
    valid = np.isfinite(values).all(axis=1)
    code = np.where(valid, 0, -1)
    filled = values.copy()
    if valid.sum() == 0:
        return filled, code
    good = np.flatnonzero(valid)
    nxt = np.searchsorted(good, np.arange(len(t_s)))  # index into good of the next valid row
    prev_row = good[np.clip(nxt - 1, 0, len(good) - 1)]
    has_prev = nxt > 0
    has_next = nxt < len(good)
    span = np.where(has_prev & has_next, t_s[good[np.clip(nxt, 0, len(good) - 1)]] - t_s[prev_row], np.inf)
    spline_rows = ~valid & has_prev & has_next & (span <= max_spline_gap_s)
    ffill_rows = ~valid & has_prev & ~spline_rows
    if spline_rows.any() and len(good) >= 2:
        filled[spline_rows] = CubicSpline(t_s[good], values[good], axis=0)(t_s[spline_rows])
        code[spline_rows] = 1
    filled[ffill_rows] = values[prev_row[ffill_rows]]
    code[ffill_rows] = 2
    return filled, code


def add_handkp_features(columns: ColumnSet, t_s: np.ndarray, options: AlignOptions) -> None:
    """Per hand: gap-filled keypoint midpoint in the camera frame and which frames were filled."""
    for hand in HANDS:
        names = [f"handkp.{hand}_{kp}_{a}_mm" for kp in ("thumb", "middle") for a in "xyz"]
        if any(columns.get(n) is None for n in names):
            continue
        keypoints = columns.stack(names)  # (N, 6): thumb xyz, middle xyz
        midpoint = (keypoints[:, :3] + keypoints[:, 3:]) / 2
        raw_valid = np.isfinite(midpoint).all(axis=1)
        filled, code = fill_gaps(t_s, midpoint, options.spline_max_gap_s)
        for k, axis in enumerate("xyz"):
            columns.add(f"handkp.{hand}_hand_{axis}_mm", filled[:, k], "mm", "handkp", frame="camera",
                        description="thumb-middle keypoint midpoint; gaps filled (see _filled)")
        columns.add(f"handkp.{hand}_filled", np.where(code < 0, np.nan, code), "code", "handkp",
                    description="0 detected, 1 cubic-spline filled (gap <= 1 s), 2 forward-filled")
        columns.add(f"handkp.{hand}_raw_valid", raw_valid.astype(float), "bool", "handkp",
                    description="1 where the hand was detected in the associated frame")


def add_clutch(columns: ColumnSet) -> None:
    """``clutch`` (0/1): robot clutch telemetry (mtm stream) where present, else the FPS clutch pedal."""
    for name, source in (("mtm.clutch", "mtm"), (f"fps.ch{CLUTCH_FPS_CHANNEL}_pressed", "fps")):
        values = columns.get(name)
        if values is not None:
            columns.add("clutch", values, "bool", source, description=f"clutch state from {name}")
            return


def downsample_rows(t_ns: np.ndarray, rate_hz: float | None) -> np.ndarray:
    """Indices of the frames kept at ``rate_hz``: the first frame of each 1/rate bin (all if None).

    Bin edges get a quarter-frame tolerance: frame times rounded to whole ns (frame 3 at 30 Hz is
    99 999 999 ns) must not slip into the previous bin and make the kept frames irregular."""
    if rate_hz is None or len(t_ns) == 0:
        return np.arange(len(t_ns))
    tolerance_ns = float(np.median(np.diff(t_ns))) / 4 if len(t_ns) > 1 else 0.0
    bins = np.floor((t_ns - t_ns[0] + tolerance_ns) * rate_hz / 1e9).astype(np.int64)
    return np.flatnonzero(np.r_[True, np.diff(bins) > 0])


def build_table(frames: np.ndarray, frame_ns: np.ndarray, columns: ColumnSet, rows: np.ndarray,
                meta: dict[str, Any]) -> AlignedTable:
    names = columns.names
    values = columns.table(rows)
    meta = {**meta, "frames": int(len(rows)), "columns": [{"name": n, **columns.meta[n]} for n in names]}
    return AlignedTable(frames[rows], frame_ns[rows], names, values, meta)


def estimate_lag(reference: np.ndarray, signal: np.ndarray, rate_hz: float, max_lag_s: float = 0.5) -> float:
    """Lag in seconds by which ``signal`` trails ``reference`` (both (N,) or (N, D) on one uniform clock
    at ``rate_hz``): the shift maximising the summed normalised cross-correlation, refined to a
    fraction of a sample by a parabola through the peak. Positive = signal is late. NaN rows ignored."""
    ref = _standardise(np.asarray(reference, dtype=float).reshape(len(reference), -1))
    sig = _standardise(np.asarray(signal, dtype=float).reshape(len(signal), -1))
    max_shift = max(1, int(round(max_lag_s * rate_hz)))
    shifts = np.arange(-max_shift, max_shift + 1)
    scores = np.array([_shifted_correlation(ref, sig, s) for s in shifts])
    if not np.isfinite(scores).any():
        raise SessionError("cannot estimate a lag: the signals have no overlapping valid samples")
    best = int(np.nanargmax(scores))
    offset = 0.0
    if 0 < best < len(scores) - 1 and np.isfinite(scores[best - 1 : best + 2]).all():
        left, mid, right = scores[best - 1 : best + 2]
        denom = left - 2 * mid + right
        offset = 0.5 * (left - right) / denom if denom < 0 else 0.0
    return float((shifts[best] + offset) / rate_hz)


def _standardise(x: np.ndarray) -> np.ndarray:
    mean, std = np.nanmean(x, axis=0), np.nanstd(x, axis=0)
    return (x - mean) / np.where(std > 0, std, 1.0)


def _shifted_correlation(ref: np.ndarray, sig: np.ndarray, shift: int) -> float:
    """Mean of ref[t] * sig[t + shift] over rows where both are valid."""
    a, b = (ref[: len(ref) - shift], sig[shift:]) if shift >= 0 else (ref[-shift:], sig[: len(sig) + shift])
    product = a * b
    ok = np.isfinite(product)
    return float(product[ok].mean()) if ok.sum() > 10 else np.nan


CALIBRATION_STEMS = tuple(f"{s}_to_{t}" for s in SOURCES for t in TARGETS)


def load_session_calibrations(session_path: Path) -> list[Calibration]:
    """Every calibration ``calibrate`` wrote into the session's ``calib/`` (emht/handkp -> mtm/psm)."""
    found = [find_calibration(session_path, f"{stem}.json") for stem in CALIBRATION_STEMS]
    return [load_calibration(path) for path in found if path is not None]


def add_calibrated(session: Session, data: dict[str, np.ndarray], columns: ColumnSet, frame_ns: np.ndarray,
                   calibration: Calibration, options: AlignOptions) -> None:
    """Columns ``<source>_<target>_<model>.<hand>_*`` from one calibration (EmHT re-associated at
    frame time + the calibration's lag, so the estimate refers to the frame's true time)."""
    prefix = f"{calibration.source}_{calibration.target}"
    if calibration.source not in data:
        return
    if calibration.source == "emht":
        lagged = ColumnSet(len(frame_ns))
        shift = {"emht": int(round(calibration.lag_ms * 1e6))}
        add_raw_streams(session, {"emht": data["emht"]}, lagged, frame_ns, options, shift)
        arrays = emht_sensor_arrays(lagged)
        if arrays is None:
            return
        points = hand_points(arrays[0])
        rotations = matrices_from_angles(arrays[1].reshape(-1, 3)).reshape(-1, 4, 3, 3) if arrays[1] is not None else None
    else:
        points = {h: columns.stack([f"handkp.{h}_hand_{a}_mm" for a in "xyz"]) for h in HANDS
                  if columns.get(f"handkp.{h}_hand_x_mm") is not None}
        rotations = None
    for model in calibration.models:
        for hand, point in points.items():
            mapped = calibration.positions(point, model)
            for k, axis in enumerate("xyz"):
                columns.add(f"{prefix}_{model}.{hand}_{axis}_mm", mapped[:, k], "mm", calibration.source,
                            frame=calibration.target, description=f"{calibration.stem} ({model}), lag {calibration.lag_ms:.1f} ms")
            if rotations is not None and calibration.has_orientation(hand):
                thumb, middle = EMHT_SENSORS[hand]
                hand_rot = calibration.orientations(rotations[:, thumb - 1], rotations[:, middle - 1], hand)
                angles = angles_from_matrices(hand_rot)
                for k, name in enumerate(("yaw", "pitch", "roll")):
                    columns.add(f"{prefix}_{model}.{hand}_{name}_deg", angles[:, k], "deg", calibration.source,
                                frame=calibration.target, description="composition of rotations (thumb and middle sensors)")


def add_robot_orientation(columns: ColumnSet) -> None:
    """``mtm.<hand>_{yaw,pitch,roll}_deg`` / ``psm...`` from the logged quaternions (for evaluation)."""
    for robot in TARGETS:
        for hand in HANDS:
            names = [f"{robot}.{hand}_q{a}" for a in "xyzw"]
            if any(columns.get(n) is None for n in names):
                continue
            angles = angles_from_matrices(matrices_from_quaternions(columns.stack(names)))
            for k, name in enumerate(("yaw", "pitch", "roll")):
                columns.add(f"{robot}.{hand}_{name}_deg", angles[:, k], "deg", robot, frame=robot,
                            description="from the logged quaternion (Rz @ Ry @ Rx convention)")


def align_session(path: Path | str, options: AlignOptions = AlignOptions(),
                  on_raw_columns: Callable[[np.ndarray], None] | None = None) -> AlignedTable:
    """Align one session (see the module docstring); does not write anything. ``on_raw_columns`` gets
    the raw streams' columns ((N, k) column-major, final, the table's first k columns) as soon as they
    are associated, when every frame is kept (``align_and_write`` starts writing them)."""
    session = Session.open(path)
    if options.clock_hz is None:
        video = session.read_columns(REFERENCE) if REFERENCE in session.stream_names else None
        frames, frame_ns = reference_frames(session, video)
        data = read_streams(session)
        time_order = time_order_warnings(session, {REFERENCE: video, **data})
    else:
        data = {name: session.read_columns(name) for name in session.stream_names}
        frames, frame_ns = regular_frames(data, options.clock_hz)
        time_order = time_order_warnings(session, data)
    t_s = (frame_ns - frame_ns[0]) / 1e9
    columns = ColumnSet(len(frames))
    covered: dict[str, dict[str, Any]] = {}
    add_raw_streams(session, data, columns, frame_ns, options, {}, covered)
    if on_raw_columns is not None and options.rate_hz is None:
        on_raw_columns(columns.table(np.arange(columns.n)))
    in_parallel(columns, [lambda c: add_emht_features(c, t_s), lambda c: add_handkp_features(c, t_s, options)])
    add_robot_orientation(columns)
    add_clutch(columns)
    calibrations = load_session_calibrations(session.path)
    for calibration in calibrations:
        add_calibrated(session, data, columns, frame_ns, calibration, options)
    meta = {
        "format": "midas-aligned-v2",  # v2: values in aligned.values.npy, no mask
        "session_id": session.manifest["session_id"],
        "reference": ("video frame times (t_host_ns of the video stream); frame = video seq"
                      if options.clock_hz is None else
                      f"regular clock at {options.clock_hz:g} Hz from the first to the last sample of any stream; "
                      "frame = tick index"),
        "clock_hz": options.clock_hz,
        "coverage": covered,
        "time_order": time_order,
        "method": options.method,
        "rate_hz": options.rate_hz,
        "stale_after_periods": options.stale_periods,
        "handkp_gap_fill": f"cubic spline for gaps <= {options.spline_max_gap_s} s, forward fill beyond",
        "sources": {s: session.manifest["streams"][s].get("sha256") for s in session.stream_names},
        "calibrations_applied": [{"file": f"calib/{c.stem}.json", "models": c.models, "lag_ms": c.lag_ms,
                                  "held_out": c.info.get("held_out"), "selected": c.choose_model(options.model),
                                  "asked": options.model, "selection": c.selection} for c in calibrations],
        "producer": provenance("midas align", asdict(options), _inputs(session, calibrations)),
    }
    return build_table(frames, frame_ns, columns, downsample_rows(frame_ns, options.rate_hz), meta)


def _inputs(session: Session, calibrations: list[Calibration]) -> dict[str, dict[str, Any]]:
    """What the aligned table was made from: each stream file (sha256 and bytes from the manifest) and
    each calibration file applied (sha256 and bytes measured now)."""
    inputs = {e["file"]: {"sha256": e.get("sha256"), "bytes": e.get("bytes")}
              for e in session.manifest["streams"].values()}
    for c in calibrations:
        path = find_calibration(session.path, f"{c.stem}.json")
        if path is not None:
            data = path.read_bytes()
            inputs[f"calib/{path.name}"] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
    return inputs


COVERAGE_WARNING = 0.95


def coverage_warnings(covered: dict[str, dict[str, Any]], options: AlignOptions) -> list[str]:
    """One line per stream of which the frame clock covers under 95% of the samples or of the time span."""
    clock = "video frame clock" if options.clock_hz is None else f"{options.clock_hz:g} Hz clock"
    lines = []
    for stream, c in covered.items():
        if min(c["samples_share"], c["span_share"]) < COVERAGE_WARNING:
            hint = "" if options.clock_hz else " (--clock RATE aligns onto a regular clock spanning every stream)"
            lines.append(f"the {clock} covers {c['samples_share']:.1%} of the samples of stream {stream!r} "
                         f"({c['samples_inside']} of {c['samples']}) and {c['span_share']:.1%} of its "
                         f"{c['span_s']:g} s span{hint}")
    return lines


def model_warnings(applied: list[dict[str, Any]]) -> list[str]:
    """One line per calibration whose MLP lost to the rigid fit on held-out trials: which one is used."""
    lines = []
    for c in applied:
        selection = c["selection"]
        if selection.get("mlp_worse_than_rigid"):
            errors = selection["held_out"]
            lines.append(f"{c['file']}: the MLP is worse than the rigid fit on held-out trials (RMSE "
                         f"{errors['mlp']['rmse_mm']:.2f} vs {errors['rigid']['rmse_mm']:.2f} mm); "
                         f"{c['selected']} is the one used (--model {c['asked']})")
    return lines


def align_and_write(path: Path | str, options: AlignOptions = AlignOptions(), csv: bool = False) -> dict[str, Any]:
    """Align one session and write ``derived/aligned.{npz,json}`` (+ ``.csv`` when ``csv``); returns a
    summary (paths, frames, columns)."""
    values_file: list[ValuesFile] = []

    def start_writing(block: np.ndarray) -> None:
        values_file.append(ValuesFile(path, len(block)))
        values_file[0].write_async(block)

    try:
        with session_lock(path):  # inputs read and outputs written by one run at a time
            table = align_session(path, options, on_raw_columns=start_writing)
            written = write_aligned(path, table, csv=csv, values_file=values_file[0] if values_file else None)
    except BaseException:
        for started in values_file:
            started.abort()
        raise
    masked = {s: float(np.isnan(table.column(s)).mean()) for s in table.columns if s.endswith("_delta_ms")}
    covered = table.meta["coverage"]
    return {"session": str(path), "frames": len(table.frame), "columns": len(table.columns),
            "masked_fraction": {k.removesuffix("_delta_ms"): round(v, 4) for k, v in masked.items()},
            "coverage": {s: {k: c[k] for k in ("samples_share", "span_share")} for s, c in covered.items()},
            "warnings": (table.meta["time_order"] + coverage_warnings(covered, options)
                         + model_warnings(table.meta["calibrations_applied"])),
            "calibrations": [c["file"] for c in table.meta["calibrations_applied"]],
            "calibration_models": {c["file"]: c["selected"] for c in table.meta["calibrations_applied"]},
            "files": {k: str(v) for k, v in written.items()}}

