"""Every stream of a session onto the video frame clock (DESIGN.md section 7): reading the session,
associating its streams on threads, applying calibrations and writing ``derived/aligned.*``. The pure
array functions are ``analysis/sync.py`` (association, gap filling, downsampling, lag estimation), the
column block ``analysis/columns.py``, the derived hand / robot columns ``analysis/hand_features.py``.

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

import hashlib
import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from midas_cli.analysis.calibration import MODEL_CHOICES, SOURCES, TARGETS, Calibration, load_calibration
from midas_cli.analysis.clockfit import fit_stream
from midas_cli.analysis.columns import ColumnSet, in_parallel
from midas_cli.analysis.hand_features import (EMHT_SENSORS, HANDS, add_clutch, add_emht_features,
                                              add_handkp_features, add_robot_orientation, emht_sensor_arrays,
                                              hand_points)
from midas_cli.analysis.sync import associate_stream, downsample_rows, regular_frames
from midas_cli.errors import ConfigError, SessionError
from midas_cli.geometry import angles_from_matrices, matrices_from_angles
from midas_cli.session.derived import AlignedTable, ValuesFile, find_calibration, write_aligned
from midas_cli.session.outputs import provenance, session_lock
from midas_cli.session.reader import Session
from midas_cli.session.values import FLOAT_LIMIT, REMEDY

log = logging.getLogger(__name__)

METHODS = ("causal", "nearest")
TIMES = ("host", "fitted")
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
    times: str = "host"  # host: the stamps as recorded; fitted: each stream's fit against its device clock

    def __post_init__(self) -> None:
        if self.times not in TIMES:
            raise ConfigError(f"--times must be one of {', '.join(TIMES)}, got {self.times!r}")
        if self.model not in MODEL_CHOICES:
            raise ConfigError(f"--calibration-model {self.model!r} is unknown "
                              f"(expected one of {', '.join(MODEL_CHOICES)})")
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


def value_columns(session: Session, stream: str) -> list[Any]:
    """The data columns of a stream: everything except seq, t_host_ns, device-clock and text columns."""
    return [c for c in session.stream_spec(stream).columns if c.clock is None and c.name != "seq" and c.dtype != "text"]


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


def read_streams(session: Session, with_reference: bool = False) -> dict[str, np.ndarray]:
    """Every stream (but the reference unless ``with_reference``) as a structured array (memory-mapped
    binary copy, or the CSV parsed when the session has none). A stream of text only (the operator's
    markers) has no value to put on a frame and is left out."""
    names = [name for name in session.stream_names if (with_reference or name != REFERENCE)
             and not (session.stream_spec(name).has_text and not value_columns(session, name))]
    # side by side: each read checks its CSV's sha256 before trusting the binary copy (hashlib lets go of
    # the GIL), which is most of the time a long session's align spends reading
    with ThreadPoolExecutor(max_workers=min(4, max(1, len(names)))) as pool:
        return dict(zip(names, pool.map(session.read_columns, names)))


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


def build_table(frames: np.ndarray, frame_ns: np.ndarray, columns: ColumnSet, rows: np.ndarray,
                meta: dict[str, Any]) -> AlignedTable:
    names = columns.names
    values = columns.table(rows)
    meta = {**meta, "frames": int(len(rows)), "columns": [{"name": n, **columns.meta[n]} for n in names]}
    return AlignedTable(frames[rows], frame_ns[rows], names, values, meta)


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


def align_session(path: Path | str, options: AlignOptions = AlignOptions(),
                  on_raw_columns: Callable[[np.ndarray], None] | None = None) -> AlignedTable:
    """Align one session (see the module docstring); does not write anything. ``on_raw_columns`` gets
    the raw streams' columns ((N, k) column-major, final, the table's first k columns) as soon as they
    are associated, when every frame is kept (``align_and_write`` starts writing them)."""
    session = Session.open(path)
    if options.clock_hz is None:
        video = session.read_columns(REFERENCE) if REFERENCE in session.stream_names else None
        data = read_streams(session)
        fits = fit_clocks(session, {REFERENCE: video, **data} if video is not None else data, options.times)
        video = fits.pop(REFERENCE, video)
        frames, frame_ns = reference_frames(session, video)
        time_order = time_order_warnings(session, {REFERENCE: video, **data})
    else:
        data = read_streams(session, with_reference=True)
        fits = fit_clocks(session, data, options.times)
        frames, frame_ns = regular_frames(data, options.clock_hz)
        time_order = time_order_warnings(session, data)
    t_s = (frame_ns - frame_ns[0]) / 1e9
    columns = ColumnSet(len(frames))
    covered: dict[str, dict[str, Any]] = {}
    add_raw_streams(session, data, columns, frame_ns, options, {}, covered)
    if on_raw_columns is not None and options.rate_hz is None:
        on_raw_columns(columns.table(np.arange(columns.n)))
    in_parallel(columns, [lambda c: add_emht_features(c, t_s), lambda c: add_handkp_features(c, t_s, options.spline_max_gap_s)])
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
        "times": options.times,
        "clock_fit": fits.pop("_stats"),
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


def fit_clocks(session: Session, data: dict[str, np.ndarray], times: str) -> dict[str, Any]:
    """Each stream's clock fit (analysis/clockfit.py) under ``"_stats"`` (stream -> its JSON); with
    ``times`` "fitted" every stream in ``data`` is replaced, there and in the result, by a copy whose
    ``t_host_ns`` are the fitted times."""
    stats: dict[str, Any] = {}
    replaced: dict[str, np.ndarray] = {}
    for name, table in data.items():
        spec = session.stream_spec(name)
        fit = fit_stream(table, spec.columns, spec.nominal_rate_hz)
        if fit is None:
            continue
        stats[name] = fit.to_json()
        if times == "fitted":
            table = np.array(table)  # a memory-mapped binary copy is read-only
            table["t_host_ns"] = fit.fitted_ns
            replaced[name] = data[name] = table
    return {**replaced, "_stats": stats}


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
                         f"{c['selected']} is the one used (--calibration-model {c['asked']})")
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

