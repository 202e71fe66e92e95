"""Fitting calibrations (EmHT or HandKP -> MTM/PSM) with leave-one-trial-out cross-validation.

Training pairs come from the raw streams on the host clock: at each robot sample time t (decimated to
about 30 Hz), the source hand point is interpolated at t + lag, where lag (how late the source is) is
estimated first from the hands' speeds, which do not depend on the unknown frames. The hand point is
the midpoint of the thumb and middle EmHT sensors (or keypoints) of that hand; both hands are pooled
into one transform. With one session there is no cross-validation and the fit uses all its data.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from midas_cli.analysis.calibration import SOURCES, TARGETS, Calibration, save_calibration
from midas_cli.analysis.hand_features import EMHT_SENSORS, HANDS, hand_points
from midas_cli.analysis.metrics import cosine_similarity, nrmse_percent
from midas_cli.analysis.sync import estimate_lag
from midas_cli.errors import ConfigError, SessionError
from midas_cli.geometry import (fit_similarity, matrices_from_angles, matrices_from_quaternions,
                                           mean_rotation, rotation_angle_deg)
from midas_cli.models.mlp_config import MLPConfig
from midas_cli.session.derived import aligned_files, calib_path
from midas_cli.session.outputs import out_target
from midas_cli.session.reader import Session

if TYPE_CHECKING:
    import pandas as pd

log = logging.getLogger(__name__)

LAG_GRID_HZ = 100.0
SPEED_HALF_WINDOW_S = 0.05


@dataclass(frozen=True)
class CalibrationOptions:
    """``rigid_only``: no MLP; ``with_scale``: fit s too (default: only for PSM targets);
    ``pair_rate_hz``: training pairs per second per hand; ``max_lag_s``: lag search range."""

    rigid_only: bool = False
    with_scale: bool | None = None
    mlp: MLPConfig = MLPConfig()
    pair_rate_hz: float = 30.0
    max_lag_s: float = 0.5
    compensate_lag: bool = True


@dataclass
class SessionPairs:
    """Paired source/target samples of one session, per hand: points (N, 3) mm; rotations (N, 3, 3)."""

    session_id: str
    lag_ms: float
    source: dict[str, np.ndarray]
    target: dict[str, np.ndarray]
    source_rot: dict[str, np.ndarray] = field(default_factory=dict)
    target_rot: dict[str, np.ndarray] = field(default_factory=dict)


def interpolate(t_ns: np.ndarray, values: np.ndarray, query_ns: np.ndarray) -> np.ndarray:
    """Linear interpolation of values (M, D) sampled at t_ns (M,) at query_ns (N,); NaN outside."""
    base = t_ns[0] if len(t_ns) else 0
    t, q = (t_ns - base) / 1e9, (query_ns - base) / 1e9
    out = np.column_stack([np.interp(q, t, values[:, d], left=np.nan, right=np.nan) for d in range(values.shape[1])])
    return out


def nearest_index(t_ns: np.ndarray, query_ns: np.ndarray) -> np.ndarray:
    """Index of the sample nearest to each query time (t_ns ascending)."""
    after = np.clip(np.searchsorted(t_ns, query_ns), 1, len(t_ns) - 1)
    return np.where(np.abs(t_ns[after] - query_ns) < np.abs(query_ns - t_ns[after - 1]), after, after - 1)


def _sorted_rows(session: Session, name: str) -> pd.DataFrame:
    """Stream ``name`` in host-time order; SessionError when it holds fewer than 2 rows (nothing to pair)."""
    data = session.read_stream(name)
    if len(data) < 2:
        raise SessionError(f"{session.path / 'streams' / (name + '.csv')}: {len(data)} data rows, a calibration "
                           "needs a recording with samples in it (record again or leave this session out)")
    return data.sort_values("t_host_ns", kind="stable")


def robot_arrays(session: Session, target: str) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Robot times (M,) ns, positions hand -> (M, 3) mm and rotations hand -> (M, 3, 3) (if logged)."""
    if target not in session.stream_names:
        raise SessionError(f"{session.path} has no {target!r} stream (robot kinematics) to calibrate against")
    data = _sorted_rows(session, target)
    t_ns = data["t_host_ns"].to_numpy(np.int64)
    pos = {h: data[[f"{h}_{a}_mm" for a in "xyz"]].to_numpy(float) for h in HANDS}
    quat_cols = {h: [f"{h}_q{a}" for a in "xyzw"] for h in HANDS}
    rot = {h: matrices_from_quaternions(data[c].to_numpy(float)) for h, c in quat_cols.items()
           if set(c) <= set(data.columns)}
    return t_ns, pos, rot


def emht_arrays(session: Session) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """EmHT times (K,) ns, sensor positions (K, 4, 3) mm and sensor rotations (K, 4, 3, 3)."""
    data = _sorted_rows(session, "emht")
    try:
        pos = data[[f"s{s}_{a}_mm" for s in range(1, 5) for a in "xyz"]].to_numpy(float).reshape(-1, 4, 3)
        ang = data[[f"s{s}_{a}_deg" for s in range(1, 5) for a in ("azimuth", "elevation", "roll")]].to_numpy(float)
    except KeyError as exc:
        raise SessionError(f"{session.path}: the emht stream needs 4 sensors with positions and angles ({exc})") from exc
    rot = matrices_from_angles(ang.reshape(-1, 3)).reshape(-1, 4, 3, 3)
    return data["t_host_ns"].to_numpy(np.int64), pos, rot


def handkp_arrays(session: Session) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """HandKP times (K,) ns and keypoint midpoints hand -> (K, 3) mm, camera frame (NaN = missed)."""
    data = _sorted_rows(session, "handkp")
    points = {}
    for hand in HANDS:
        thumb = data[[f"{hand}_thumb_{a}_mm" for a in "xyz"]].to_numpy(float)
        middle = data[[f"{hand}_middle_{a}_mm" for a in "xyz"]].to_numpy(float)
        points[hand] = (thumb + middle) / 2
    return data["t_host_ns"].to_numpy(np.int64), points


def speed_lag_s(ref_t: np.ndarray, ref: dict[str, np.ndarray], src_t: np.ndarray, src: dict[str, np.ndarray],
                max_lag_s: float) -> float:
    """How late (s) the source hand points are relative to the reference, from their speed profiles
    (frame-independent) on a common 100 Hz grid."""
    start, stop = max(ref_t[0], src_t[0]), min(ref_t[-1], src_t[-1])
    if stop - start < 2e9:
        raise SessionError("source and robot streams overlap for less than 2 s: cannot estimate their lag")
    grid = np.arange(start, stop, int(1e9 / LAG_GRID_HZ))
    half = int(round(SPEED_HALF_WINDOW_S * LAG_GRID_HZ))

    def speeds(t_ns: np.ndarray, points: dict[str, np.ndarray]) -> np.ndarray:
        cols = []
        for hand in HANDS:
            p = interpolate(t_ns, points[hand], grid)
            v = np.full(len(grid), np.nan)
            v[half:-half] = np.linalg.norm(p[2 * half:] - p[: -2 * half], axis=1) / (2 * SPEED_HALF_WINDOW_S)
            cols.append(v)
        return np.column_stack(cols)

    return estimate_lag(speeds(ref_t, ref), speeds(src_t, src), LAG_GRID_HZ, max_lag_s)


def emht_pairs(session: Session, target: str, options: CalibrationOptions) -> SessionPairs:
    """EmHT hand points (and thumb-sensor rotations) paired with robot poses of one session."""
    robot_t, robot_pos, robot_rot = robot_arrays(session, target)
    em_t, em_pos, em_rot = emht_arrays(session)
    points = hand_points(em_pos)
    lag_s = speed_lag_s(robot_t, robot_pos, em_t, points, options.max_lag_s) if options.compensate_lag else 0.0
    keep = _decimate(robot_t, options.pair_rate_hz)
    query = robot_t[keep] + int(round(lag_s * 1e9))
    idx = nearest_index(em_t, query)
    pairs = SessionPairs(session.manifest["session_id"], lag_s * 1e3, {}, {})
    for hand in HANDS:
        pairs.source[hand] = interpolate(em_t, points[hand], query)
        pairs.target[hand] = robot_pos[hand][keep]
        if hand in robot_rot:
            thumb, middle = EMHT_SENSORS[hand]
            pairs.source_rot[f"{hand}_thumb"] = em_rot[idx, thumb - 1]
            pairs.source_rot[f"{hand}_middle"] = em_rot[idx, middle - 1]
            pairs.target_rot[hand] = robot_rot[hand][keep]
    return pairs


def handkp_pairs(session: Session, target: str, options: CalibrationOptions) -> SessionPairs:
    """Detected HandKP midpoints (camera frame) paired with robot positions at the same true time."""
    robot_t, robot_pos, _ = robot_arrays(session, target)
    kp_t, points = handkp_arrays(session)
    lag_s = speed_lag_s(robot_t, robot_pos, kp_t, points, options.max_lag_s) if options.compensate_lag else 0.0
    query = kp_t - int(round(lag_s * 1e9))
    pairs = SessionPairs(session.manifest["session_id"], lag_s * 1e3, {}, {})
    for hand in HANDS:
        pairs.source[hand] = points[hand]
        pairs.target[hand] = interpolate(robot_t, robot_pos[hand], query)
    return pairs


def fit_calibration(pairs: list[SessionPairs], source: str, target: str, options: CalibrationOptions) -> Calibration:
    """Rigid/similarity fit (+ MLP) on the pooled pairs of ``pairs``."""
    src = np.concatenate([p.source[h] for p in pairs for h in HANDS])
    dst = np.concatenate([p.target[h] for p in pairs for h in HANDS])
    with_scale = (target == "psm") if options.with_scale is None else options.with_scale
    rotation, translation, scale = fit_similarity(src, dst, with_scale)
    calibration = Calibration(source, target, rotation, translation, scale,
                              lag_ms=float(np.mean([p.lag_ms for p in pairs])) if source == "emht" else 0.0,
                              info={"trained_on": [p.session_id for p in pairs],
                                    "lag_ms_per_session": {p.session_id: round(p.lag_ms, 3) for p in pairs}})
    if source == "emht":
        calibration.orientation_offsets = _orientation_offsets(pairs, rotation)
    if not options.rigid_only:
        from midas_cli.models.residual_mlp import train_mlp  # torch: imported only when an MLP is trained

        residual_target = dst if source == "handkp" else dst - calibration.positions(src, "rigid")
        calibration.mlp = train_mlp(src, residual_target, options.mlp, center_output=True)
    return calibration


def evaluate_calibration(calibration: Calibration, pairs: SessionPairs) -> dict[str, Any]:
    """Held-out metrics per model: RMSE (mm), CoS and NRMSE(%) per axis, orientation error (deg)."""
    result: dict[str, Any] = {"session": pairs.session_id, "lag_ms": round(pairs.lag_ms, 3)}
    for model in calibration.models:
        pred = np.concatenate([calibration.positions(pairs.source[h], model) for h in HANDS])
        truth = np.concatenate([pairs.target[h] for h in HANDS])
        err = np.linalg.norm(pred - truth, axis=1)
        scores = {"rmse_mm": float(np.sqrt(np.nanmean(err ** 2)))}
        for k, axis in enumerate("xyz"):
            scores[f"cos_{axis}"] = cosine_similarity(pred[:, k], truth[:, k])
            scores[f"nrmse_{axis}"] = nrmse_percent(pred[:, k], truth[:, k])
        result[model] = scores
    if calibration.orientation_offsets and pairs.target_rot:
        result["orientation_error_deg"] = _orientation_error(calibration, pairs)
    return result


def cross_validate(pairs: list[SessionPairs], source: str, target: str, options: CalibrationOptions,
                   progress: Callable[[str], None] = lambda _: None
                   ) -> tuple[Calibration, dict[str, Calibration], list[dict[str, Any]]]:
    """Leave-one-trial-out: returns (model on all sessions, held-out model per session, fold metrics)."""
    if source not in SOURCES or target not in TARGETS:
        raise ConfigError(f"cannot calibrate {source} -> {target} (sources {SOURCES}, targets {TARGETS})")
    folds: dict[str, Calibration] = {}
    metrics: list[dict[str, Any]] = []
    if len(pairs) >= 2:
        for held in pairs:
            progress(f"fold: holding out {held.session_id}")
            model = fit_calibration([p for p in pairs if p is not held], source, target, options)
            model.info = {**model.info, "held_out": held.session_id,
                          "note": "leave-one-trial-out fold: this session was not used to fit this model"}
            folds[held.session_id] = model
            metrics.append(evaluate_calibration(model, held))
    progress("final model on all sessions")
    final = fit_calibration(pairs, source, target, options)
    final.info = {**final.info, "held_out": None, "cv": summarise_folds(metrics)}
    return final, folds, metrics


def summarise_folds(metrics: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean over folds of every numeric held-out metric, per model."""
    summary: dict[str, Any] = {"folds": len(metrics)}
    for model in ("rigid", "mlp"):
        rows = [m[model] for m in metrics if model in m]
        if rows:
            summary[model] = {k: float(np.nanmean([r[k] for r in rows])) for k in rows[0]}
    errors = [m["orientation_error_deg"] for m in metrics if "orientation_error_deg" in m]
    if errors:
        summary["orientation_error_deg"] = float(np.nanmean(errors))
    return summary


def select_model(cv: dict[str, Any], models: list[str]) -> dict[str, Any]:
    """Which model ``align``/``eval`` use by default (``--calibration-model best``): the MLP only when its mean
    held-out RMSE over the leave-one-trial-out folds is no worse than the rigid fit's. Both held-out
    errors are kept; without folds (one session) nothing is compared and the MLP stays the default."""
    if "mlp" not in models:
        return {"best": "rigid", "compared": False, "reason": "no MLP fitted (--rigid-only)"}
    if not cv.get("folds") or "rigid" not in cv or "mlp" not in cv:
        return {"best": "mlp", "compared": False,
                "reason": "no held-out trials (one session): the MLP was not checked against the rigid fit"}
    held_out = {m: {"rmse_mm": cv[m]["rmse_mm"], "cos": float(np.nanmean([cv[m][f"cos_{a}"] for a in "xyz"]))}
                for m in ("rigid", "mlp")}
    worse = not held_out["mlp"]["rmse_mm"] <= held_out["rigid"]["rmse_mm"]  # NaN counts as worse
    return {"best": "rigid" if worse else "mlp", "compared": True, "folds": cv["folds"],
            "held_out": held_out, "mlp_worse_than_rigid": worse,
            "reason": "mean held-out RMSE over the leave-one-trial-out folds (every fold, this session's too)"}


def _orientation_offsets(pairs: list[SessionPairs], rotation: np.ndarray) -> dict[str, np.ndarray]:
    """Per sensor O = chordal mean over samples of (R R_sensor)^T R_target (composition of rotations)."""
    offsets = {}
    for hand in HANDS:
        dst = [p.target_rot[hand] for p in pairs if hand in p.target_rot]
        for finger in ("thumb", "middle"):
            src = [p.source_rot[f"{hand}_{finger}"] for p in pairs if f"{hand}_{finger}" in p.source_rot]
            if src and dst:
                rel = np.swapaxes(rotation @ np.concatenate(src), 1, 2) @ np.concatenate(dst)
                offsets[f"{hand}_{finger}"] = mean_rotation(rel)
    return offsets


def _orientation_error(calibration: Calibration, pairs: SessionPairs) -> float:
    """Mean angle (deg) between predicted and logged robot orientations over both hands."""
    angles = []
    for hand in HANDS:
        if hand not in pairs.target_rot or not calibration.has_orientation(hand):
            continue
        pred = calibration.orientations(pairs.source_rot[f"{hand}_thumb"], pairs.source_rot[f"{hand}_middle"], hand)
        ok = np.isfinite(pred).all(axis=(1, 2)) & np.isfinite(pairs.target_rot[hand]).all(axis=(1, 2))
        angles += [rotation_angle_deg(a, b) for a, b in zip(pred[ok][::10], pairs.target_rot[hand][ok][::10])]
    return float(np.mean(angles)) if angles else float("nan")


def _decimate(t_ns: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices keeping about ``rate_hz`` samples per second."""
    if len(t_ns) < 2:
        return np.arange(len(t_ns))
    native = (len(t_ns) - 1) / max((t_ns[-1] - t_ns[0]) / 1e9, 1e-9)
    return np.arange(0, len(t_ns), max(1, int(round(native / rate_hz))))


def calibrate_sessions(paths: list[Path], source: str, target: str, options: CalibrationOptions,
                       out: Path | None = None, progress: Callable[[str], None] = lambda _: None) -> dict[str, Any]:
    """Pair, cross-validate and write calibrations. Each session's ``calib/<source>_to_<target>.json``
    gets the model that did NOT see it (its leave-one-trial-out fold; with one session, the model fitted
    on it); ``out`` (a .json path) gets the model fitted on all sessions. Returns a JSON-able report."""
    build = emht_pairs if source == "emht" else handkp_pairs
    if out is not None:  # checked before the fit: never a session's own file (the weights go beside it)
        read = [file for path in paths for file in aligned_files(path)]
        out = out_target(out, inputs=read)
        out_target(out.with_suffix(".pt"), inputs=read)
    pairs = []
    for path in paths:
        progress(f"pairing {Path(path).name}")
        pairs.append(build(Session.open(path), target, options))
    final, folds, metrics = cross_validate(pairs, source, target, options, progress)
    selection = select_model(final.info["cv"], final.models)
    for model in (final, *folds.values()):
        model.info = {**model.info, "selection": selection}
    written: dict[str, list[str]] = {}
    for path, pair in zip(paths, pairs):
        model = folds.get(pair.session_id, final)
        written[str(path)] = [str(p) for p in save_calibration(model, calib_path(path, f"{model.stem}.json"))]
    if out is not None:
        written["all"] = [str(p) for p in save_calibration(final, out)]
    return {"source": source, "target": target, "sessions": len(paths),
            "rigid": {"R": final.rotation.tolist(), "t_mm": final.translation.tolist(), "scale": final.scale},
            "lag_ms": final.lag_ms, "models": final.models, "folds": metrics, "cv": final.info["cv"],
            "selection": selection, "written": written}
