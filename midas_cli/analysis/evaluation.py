"""The paper's validation tables from aligned sessions: trajectory correlation, grasper states, pedals.

Inputs are aligned tables (``derived/aligned.npz``). Per-session rows are long-format dictionaries;
``summarise`` averages them over sessions (trials) and hands into the paper's table layouts.
* correlation: CoS and NRMSE per axis for EmHT-MTM, EmHT-PSM, HandKP-MTM, HandKP-PSM (model "mlp"
  where calibrated with one, else "rigid"); HandKP also on detected frames only (Appendix A.3).
  Angles are unwrapped before scoring.
* grasper: PSM-MTM, EmHT-MTM, EmHT-PSM closed-state IoU, accuracy, precision (Appendix A.2.2).
* pedals: per pedal and overall (pooled over pedals with ground-truth presses) precision, recall, F1,
  temporal IoU and lag (ms) against the robot clutch (``mtm.clutch``) or ``derived/pedals_gt.csv``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from midas_cli.analysis.hand_features import HANDS
from midas_cli.analysis.metrics import (best_lag_frames, binary_scores, closed_states, cosine_similarity,
                                        nrmse_percent, temporal_iou)
from midas_cli.analysis.sync import estimate_lag
from midas_cli.devices.pedals import adc_to_volts
from midas_cli.geometry import unwrap_deg
from midas_cli.session.derived import AlignedTable

COMPARISONS = (("EmHT-MTM", "emht", "mtm"), ("EmHT-PSM", "emht", "psm"),
               ("HandKP-MTM", "handkp", "mtm"), ("HandKP-PSM", "handkp", "psm"))
AXES = (("X", "x_mm"), ("Y", "y_mm"), ("Z", "z_mm"), ("Roll", "roll_deg"), ("Pitch", "pitch_deg"), ("Yaw", "yaw_deg"))
PEDAL_CHANNELS = {"secondary_energy_left": 1, "secondary_energy_right": 2, "primary_energy_left": 3,
                  "primary_energy_right": 4, "clutch": 5, "camera": 6, "arm_swap": 7}
GRASPER_WINDOW_S = 0.5
MAX_PEDAL_LAG_S = 1.0


@dataclass(frozen=True)
class PedalRule:
    """A pressed state from the raw FSR voltage: pressed when volts >= threshold ("above") or <= ("below")."""

    threshold_v: float
    polarity: str = "above"

    def apply(self, volts: np.ndarray) -> np.ndarray:
        pressed = volts >= self.threshold_v if self.polarity == "above" else volts <= self.threshold_v
        return np.where(np.isfinite(volts), pressed.astype(float), np.nan)


def frame_rate_hz(table: AlignedTable) -> float:
    """Median frame rate of the aligned table (Hz)."""
    steps = np.diff(table.t_host_ns)
    return float(1e9 / np.median(steps)) if len(steps) else float("nan")


def models_for(table: AlignedTable, source: str, target: str) -> list[str]:
    """Calibrated models present in the table for source -> target ("rigid", "mlp")."""
    return [m for m in ("rigid", "mlp") if table.has(f"{source}_{target}_{m}.left_x_mm")
            or table.has(f"{source}_{target}_{m}.right_x_mm")]


def correlation_rows(table: AlignedTable, session: str) -> list[dict[str, Any]]:
    """One row per (comparison, model, subset, hand, axis) with CoS and NRMSE(%)."""
    rows = []
    for name, source, target in COMPARISONS:
        for model in models_for(table, source, target):
            subsets = ("all", "detected") if source == "handkp" else ("all",)
            for subset in subsets:
                for hand in HANDS:
                    rows += _axis_rows(table, session, name, f"{source}_{target}_{model}", target, model, subset, hand)
    return rows


def _axis_rows(table: AlignedTable, session: str, name: str, prefix: str, target: str, model: str, subset: str,
               hand: str) -> list[dict[str, Any]]:
    keep = np.ones(len(table.frame), bool)
    if subset == "detected" and table.has(f"handkp.{hand}_raw_valid"):
        keep = table.column(f"handkp.{hand}_raw_valid") > 0.5
    rows = []
    for axis, suffix in AXES:
        pred_name, truth_name = f"{prefix}.{hand}_{suffix}", f"{target}.{hand}_{suffix}"
        if not (table.has(pred_name) and table.has(truth_name)):
            continue
        pred, truth = table.column(pred_name), table.column(truth_name)
        if suffix.endswith("_deg"):
            pred, truth = unwrap_deg(pred), unwrap_deg(truth)
        pred, truth = np.where(keep, pred, np.nan), np.where(keep, truth, np.nan)
        rows.append({"session": session, "comparison": name, "model": model, "subset": subset, "hand": hand,
                     "axis": axis, "cos": cosine_similarity(pred, truth), "nrmse": nrmse_percent(pred, truth),
                     "frames": int(np.sum(np.isfinite(pred) & np.isfinite(truth)))})
    return rows


def grasper_states(table: AlignedTable) -> dict[str, dict[str, np.ndarray]]:
    """Closed (1) / open (0) per frame per hand for "MTM", "PSM" (grasper angle) and "EmHT" (sensor distance,
    moving average over 0.5 s); each binarised at its own midpoint threshold."""
    window = max(1, int(round(GRASPER_WINDOW_S * frame_rate_hz(table))))
    states: dict[str, dict[str, np.ndarray]] = {}
    for hand in HANDS:
        for label, column, smooth in (("MTM", f"mtm.{hand}_grasper_deg", 1), ("PSM", f"psm.{hand}_grasper_deg", 1),
                                      ("EmHT", f"emht.{hand}_grasper_mm", window)):
            if table.has(column):
                states.setdefault(label, {})[hand] = closed_states(table.column(column), window=smooth)[0]
    return states


def grasper_rows(table: AlignedTable, session: str) -> list[dict[str, Any]]:
    """IoU, accuracy, precision of closed states for PSM-MTM, EmHT-MTM, EmHT-PSM, per hand."""
    states = grasper_states(table)
    rows = []
    for pred, truth in (("PSM", "MTM"), ("EmHT", "MTM"), ("EmHT", "PSM")):
        for hand in HANDS:
            if hand in states.get(pred, {}) and hand in states.get(truth, {}):
                s = binary_scores(states[pred][hand], states[truth][hand])
                rows.append({"session": session, "comparison": f"{pred}-{truth}", "hand": hand, "iou": s.iou,
                             "accuracy": s.accuracy, "precision": s.precision})
    return rows


def lag_rows(table: AlignedTable, session: str) -> list[dict[str, Any]]:
    """Lag (ms) of EmHT and HandKP hand points behind the robot's, from speed cross-correlation on frames."""
    rate = frame_rate_hz(table)
    rows = []
    for name, source, target in COMPARISONS:
        ref, sig = [], []
        for hand in HANDS:
            src_cols = [f"{source}.{hand}_hand_{a}_mm" for a in "xyz"]
            dst_cols = [f"{target}.{hand}_{a}_mm" for a in "xyz"]
            if all(table.has(c) for c in src_cols + dst_cols):
                sig.append(_speed(np.column_stack([table.column(c) for c in src_cols]), rate))
                ref.append(_speed(np.column_stack([table.column(c) for c in dst_cols]), rate))
        if ref:
            lag = estimate_lag(np.column_stack(ref), np.column_stack(sig), rate, max_lag_s=0.5)
            rows.append({"session": session, "comparison": name, "lag_ms": lag * 1e3})
    return rows


def _speed(points: np.ndarray, rate_hz: float) -> np.ndarray:
    """Speed (N,) mm/s by central differences over +/-2 frames."""
    speed = np.full(len(points), np.nan)
    if len(points) > 4:
        speed[2:-2] = np.linalg.norm(points[4:] - points[:-4], axis=1) * rate_hz / 4
    return speed


def pedal_truth(table: AlignedTable, gt: pd.DataFrame | None) -> dict[str, np.ndarray]:
    """Ground-truth pressed states per pedal name on the table's frames: ``pedals_gt.csv`` columns where
    given (matched by frame), else the robot clutch (``mtm.clutch``)."""
    if gt is not None:
        indexed = gt.drop_duplicates("frame").set_index("frame")
        return {p: indexed[p].reindex(table.frame).to_numpy(float) for p in PEDAL_CHANNELS if p in indexed.columns}
    if table.has("mtm.clutch"):
        return {"clutch": table.column("mtm.clutch")}
    return {}


def pedal_detection(table: AlignedTable, pedal: str, rule: PedalRule | None = None) -> np.ndarray | None:
    """FPS pressed state of a pedal's channel per frame: the recorded state, or ``rule`` on the raw voltage."""
    channel = PEDAL_CHANNELS[pedal]
    if rule is not None and table.has(f"fps.ch{channel}_adc"):
        return rule.apply(adc_to_volts(table.column(f"fps.ch{channel}_adc")))
    name = f"fps.ch{channel}_pressed"
    return table.column(name) if table.has(name) else None


def pedal_rows(table: AlignedTable, session: str, truth: dict[str, np.ndarray],
               rules: dict[str, PedalRule] | None = None) -> list[dict[str, Any]]:
    """Per pedal: precision, recall, F1, temporal IoU, lag (ms), ground-truth usage (% of frames)."""
    rate, t_s = frame_rate_hz(table), table.times_s()
    rows = []
    for pedal, gt in truth.items():
        det = pedal_detection(table, pedal, (rules or {}).get(pedal))
        if det is None:
            continue
        s = binary_scores(det, gt)
        lag = best_lag_frames(det, gt, int(round(MAX_PEDAL_LAG_S * rate))) * 1e3 / rate if s.tp + s.fn > 0 else np.nan
        rows.append({"session": session, "pedal": pedal, "channel": PEDAL_CHANNELS[pedal], "precision": s.precision,
                     "recall": s.recall, "f1": s.f1, "iou": temporal_iou(det, gt, t_s), "lag_ms": lag,
                     "usage_pct": 100 * float(np.nanmean(gt)), "tp": s.tp, "fp": s.fp, "fn": s.fn, "tn": s.tn})
    return rows


def overall_pedal_row(rows: list[dict[str, Any]]) -> dict[str, Any] | None:
    """One session's overall scores, pooled over pedals with ground-truth presses (micro average);
    IoU and lag are averaged over those pedals."""
    used = [r for r in rows if r["tp"] + r["fn"] > 0]
    if not used:
        return None
    tp, fp, fn = (sum(r[k] for r in used) for k in ("tp", "fp", "fn"))
    ratio = lambda a, b: a / b if b else float("nan")  # noqa: E731
    return {"session": used[0]["session"], "pedal": "overall", "channel": 0, "precision": ratio(tp, tp + fp),
            "recall": ratio(tp, tp + fn), "f1": ratio(2 * tp, 2 * tp + fp + fn),
            "iou": float(np.nanmean([r["iou"] for r in used])), "lag_ms": float(np.nanmean([r["lag_ms"] for r in used])),
            "usage_pct": float(np.nansum([r["usage_pct"] for r in used])), "tp": tp, "fp": fp, "fn": fn,
            "tn": sum(r["tn"] for r in used)}


def summarise(rows: list[dict[str, Any]], keys: list[str], values: list[str]) -> pd.DataFrame:
    """Mean of ``values`` over sessions (and anything not in ``keys``), grouped by ``keys``; adds ``n``
    (number of sessions)."""
    frame = pd.DataFrame(rows)
    if frame.empty:
        return pd.DataFrame(columns=[*keys, *values, "n"])
    grouped = frame.groupby(keys, sort=False)
    summary = grouped[values].mean().reset_index()
    summary["n"] = grouped["session"].nunique().to_numpy()
    return summary


def correlation_table(rows: list[dict[str, Any]]) -> pd.DataFrame:
    """The paper's correlation table: one row per comparison (the chosen model, all frames), CoS/NRMSE
    per axis. Rows carry ``selected`` (the model chosen for their session, see eval_runs.model_choices);
    without it the MLP is preferred where present."""
    frame = pd.DataFrame(rows)
    if frame.empty:
        return frame
    best = frame[frame["subset"] == "all"].copy()
    if "selected" in best:
        best = best[best["selected"].astype(bool)]
    else:
        best["rank"] = best["model"].map({"mlp": 0, "rigid": 1})
        best = best[best["rank"] == best.groupby("comparison")["rank"].transform("min")]
    return _wide(summarise(best.to_dict("records"), ["comparison", "model", "axis"], ["cos", "nrmse"]),
                 ["comparison", "model"])


def handkp_table(rows: list[dict[str, Any]], subset: str) -> pd.DataFrame:
    """Appendix A.3 tables: HandKP->MTM by model (rigid, MLP) on all frames or detected frames only."""
    frame = pd.DataFrame(rows)
    if frame.empty:
        return frame
    chosen = frame[(frame["comparison"] == "HandKP-MTM") & (frame["subset"] == subset)]
    return _wide(summarise(chosen.to_dict("records"), ["model", "axis"], ["cos", "nrmse"]), ["model"])


def mark_worse(table: pd.DataFrame, worse: dict[str, Any], comparison: str | None = None) -> pd.DataFrame:
    """``model`` "mlp" -> "mlp*" in the rows of comparisons in ``worse`` (their MLP lost to the rigid fit
    on held-out trials); ``comparison`` names it for a table without a comparison column."""
    if table.empty or not worse:
        return table
    table = table.copy()
    names = table["comparison"] if "comparison" in table else pd.Series(comparison, index=table.index)
    table.loc[(table["model"] == "mlp") & names.isin(list(worse)), "model"] = "mlp*"
    return table


def _wide(summary: pd.DataFrame, index: list[str]) -> pd.DataFrame:
    """Long (index, axis, cos, nrmse, n) -> one row per index with ``<Axis> CoS`` / ``<Axis> NRMSE`` columns."""
    if summary.empty:
        return summary
    out = summary.pivot_table(index=index, columns="axis", values=["cos", "nrmse"], sort=False)
    axes = [a for a, _ in AXES if a in set(summary["axis"])]
    columns = {f"{a} {label}": out[(metric, a)] for a in axes for metric, label in (("cos", "CoS"), ("nrmse", "NRMSE"))}
    counts = summary.groupby(index, sort=False)["n"].max().reset_index()
    return pd.DataFrame(columns).reset_index().merge(counts, on=index, how="left")
