"""`eval correlation` / `eval pedals` / `calibrate fps-optimize` over many aligned sessions: collect
per-session rows, average them into the paper's tables, write files and figures."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from midas_cli.analysis import evaluation as ev
from midas_cli.analysis.calibration import MODEL_CHOICES
from midas_cli.analysis.figures import grasper_figure, pedal_figure, trajectory_figure
from midas_cli.analysis.metrics import binary_scores
from midas_cli.analysis.report import json_safe, write_tables
from midas_cli.devices.pedals import adc_to_volts
from midas_cli.errors import ConfigError, SessionError
from midas_cli.session.derived import (PEDALS_GT, AlignedTable, aligned_files, calib_path, find_calibration,
                                       output_dir, read_aligned, read_pedals_ground_truth)
from midas_cli.session.outputs import out_folder, out_target, write_json
from midas_cli.session.reader import Session

FPS_RULES_FILE = "fps_optimized.json"


@dataclass
class EvalResult:
    """Tables (key -> (DataFrame, caption)), per-session rows, files written, data provenance."""

    tables: dict[str, tuple[pd.DataFrame, str]]
    rows: dict[str, list[dict[str, Any]]]
    files: list[Path] = field(default_factory=list)
    provenance: dict[str, Any] = field(default_factory=dict)


def data_label(paths: list[Path]) -> str:
    """"simulated" when every session was written by a simulator, "recorded" when none, else "mixed"."""
    simulated = [Session.open(p).manifest.get("stop_reason") == "simulated" for p in paths]
    return "simulated" if all(simulated) else ("recorded" if not any(simulated) else "mixed (simulated and recorded)")


def _provenance(paths: list[Path], tables: list[AlignedTable]) -> dict[str, Any]:
    label = data_label(paths)
    return {"data_label": f"{label} data, {len(paths)} session(s)", "sessions": [str(p) for p in paths],
            "aligned": [{"session": t.meta.get("session_id"), "method": t.meta.get("method"),
                         "calibrations": t.meta.get("calibrations_applied", [])} for t in tables]}


def _default_out(paths: list[Path], out: Path | None) -> Path:
    if out is not None:
        return out_folder(out)
    if len(paths) == 1:
        return output_dir(paths[0], "eval")
    raise SessionError("several sessions given: say where the averaged tables go with --out DIR")


def model_choices(table: AlignedTable, wanted: str = "best") -> tuple[dict[str, str], dict[str, dict]]:
    """Per comparison ("EmHT-MTM", ...) the calibration model to report, and the held-out comparisons
    (calibrate's ``selection``) of those whose MLP was worse than the rigid fit. ``wanted`` best = the
    model ``align`` recorded (calibrate's held-out winner unless align was told otherwise); rigid|mlp
    force it where fitted. An aligned table from an older midas has no record: the MLP when present."""
    if wanted not in MODEL_CHOICES:
        raise ConfigError(f"--calibration-model {wanted!r} is unknown (expected one of {', '.join(MODEL_CHOICES)})")
    names = {f"{source}_to_{target}": name for name, source, target in ev.COMPARISONS}
    applied = {names[Path(a["file"]).stem]: a for a in table.meta.get("calibrations_applied", [])
               if Path(a["file"]).stem in names}
    chosen, worse = {}, {}
    for name, source, target in ev.COMPARISONS:
        models = ev.models_for(table, source, target)
        if not models:
            continue
        record = applied.get(name, {})
        pick = record.get("selected") if wanted == "best" else wanted
        chosen[name] = pick if pick in models else models[-1]
        if (record.get("selection") or {}).get("mlp_worse_than_rigid"):
            worse[name] = record["selection"]
    return chosen, worse


def run_correlation(paths: list[Path], out: Path | None, plots: bool,
                    progress: Callable[[str], None] = lambda _: None, model: str = "best") -> EvalResult:
    """CoS/NRMSE, grasper and lag tables averaged over ``paths``; figures per session when ``plots``.
    ``model`` (best|rigid|mlp, see :func:`model_choices`) picks the calibration model of the main
    table; an MLP worse than the rigid fit on held-out trials is marked "mlp*" wherever it is listed."""
    out = _default_out(paths, out) if out is not None or len(paths) != 1 else None  # a bad --out fails first
    rows: dict[str, list[dict[str, Any]]] = {"correlation": [], "grasper": [], "lag": []}
    tables = []
    files: list[Path] = []
    worse: dict[str, dict] = {}
    for path in paths:
        progress(Path(path).name)
        table = read_aligned(path)
        session = table.meta.get("session_id", Path(path).name)
        chosen, session_worse = model_choices(table, model)
        worse.update(session_worse)
        rows["correlation"] += [{**r, "selected": r["model"] == chosen.get(r["comparison"])}
                                for r in ev.correlation_rows(table, session)]
        rows["grasper"] += ev.grasper_rows(table, session)
        rows["lag"] += ev.lag_rows(table, session)
        tables.append(table)
        if plots:
            files += correlation_figures(path, table, chosen)
    result = EvalResult(correlation_tables(rows, worse), rows, files, _provenance(paths, tables))
    result.files += write_tables(_default_out(paths, out), "correlation", result.tables, rows, result.provenance)
    return result


def worse_note(worse: dict[str, dict]) -> str:
    """Caption footnote for rows marked "mlp*" (empty when none is)."""
    if not worse:
        return ""
    parts = [f"{name}: RMSE {s['held_out']['mlp']['rmse_mm']:.2f} vs {s['held_out']['rigid']['rmse_mm']:.2f} mm"
             for name, s in sorted(worse.items())]
    return (f"; * MLP worse than the rigid fit on held-out trials ({'; '.join(parts)}), "
            "so --calibration-model best uses the rigid fit")


def correlation_tables(rows: dict[str, list[dict[str, Any]]],
                       worse: dict[str, dict] | None = None) -> dict[str, tuple[pd.DataFrame, str]]:
    n = len({r["session"] for r in rows["correlation"] + rows["grasper"] + rows["lag"]})
    worse = worse or {}
    handkp_worse = {k: v for k, v in worse.items() if k == "HandKP-MTM"}
    main = ev.mark_worse(ev.correlation_table(rows["correlation"]), worse)
    marked = set() if main.empty else set(main.loc[main["model"] == "mlp*", "comparison"])
    shown = {c: v for c, v in worse.items() if c in marked}
    return {
        "correlation": (main, f"Mean CoS and NRMSE(%) per axis over {n} trial(s) and both hands" + worse_note(shown)),
        "grasper": (ev.summarise(rows["grasper"], ["comparison"], ["iou", "accuracy", "precision"]),
                    f"Grasper open/close IoU, accuracy, precision over {n} trial(s) and both hands"),
        "handkp_all_frames": (ev.mark_worse(ev.handkp_table(rows["correlation"], "all"), handkp_worse, "HandKP-MTM"),
                              "HandKP estimation of the MTM trajectory (gaps filled)" + worse_note(handkp_worse)),
        "handkp_detected_frames": (ev.mark_worse(ev.handkp_table(rows["correlation"], "detected"), handkp_worse,
                                                 "HandKP-MTM"),
                                   "HandKP estimation of the MTM trajectory (ignoring missing data)"
                                   + worse_note(handkp_worse)),
        "lag": (ev.summarise(rows["lag"], ["comparison"], ["lag_ms"]),
                "Lag of the hand modality behind the robot kinematics (speed cross-correlation)"),
    }


def correlation_figures(path: Path, table: AlignedTable, chosen: dict[str, str]) -> list[Path]:
    """Per session and hand: trajectory overlays (MTM and PSM side by side) for each calibrated source
    (the ``chosen`` model per comparison), and grasper states; titled with the session's name."""
    folder = output_dir(path, "plots")
    files = []
    session_name = Path(path).resolve().name
    for source in dict.fromkeys(source for _, source, _ in ev.COMPARISONS):
        prefixes = {target: f"{source}_{target}_{chosen[name]}" for name, s, target in ev.COMPARISONS
                    if s == source and name in chosen}
        models = ", ".join(f"{target.upper()}: {chosen[name]}" for name, s, target in ev.COMPARISONS
                           if s == source and name in chosen)
        for hand in ("left", "right") if prefixes else ():
            drawn = trajectory_figure(table, hand, prefixes, folder / f"trajectory_{source}_{hand}.png",
                                      f"{session_name}: {source} calibrated onto MTM / PSM ({models}), {hand} hand")
            files += [drawn] if drawn else []
    states = ev.grasper_states(table)
    for hand in ("left", "right"):
        by_source = {label: by_hand[hand] for label, by_hand in states.items() if hand in by_hand}
        if by_source:
            files.append(grasper_figure(table.times_s(), by_source, folder / f"grasper_{hand}.png",
                                        f"{session_name}: {hand} grasper"))
    return files


def load_rules(path: Path) -> dict[str, ev.PedalRule]:
    """Pedal rules from a ``calibrate fps-optimize`` file (``calib/fps_optimized.json``)."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
        return {p: ev.PedalRule(float(r["threshold_v"]), r["polarity"]) for p, r in data["pedals"].items()}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SessionError(f"cannot read pedal thresholds {path}: {exc}") from exc


def run_pedals(paths: list[Path], out: Path | None, plots: bool, use_optimized: bool,
               progress: Callable[[str], None] = lambda _: None) -> EvalResult:
    """Per pedal and overall precision/recall/F1/IoU/lag averaged over ``paths``."""
    out = _default_out(paths, out) if out is not None or len(paths) != 1 else None  # a bad --out fails first
    rows: list[dict[str, Any]] = []
    tables, files = [], []
    for path in paths:
        progress(Path(path).name)
        table = read_aligned(path)
        truth = ev.pedal_truth(table, read_pedals_ground_truth(path))
        if not truth:
            raise SessionError(f"{path} has no pedal ground truth: neither derived/pedals_gt.csv nor an mtm "
                               f"clutch column (run `midas extract pedals` or align a Raven-II session)")
        rules_file = find_calibration(path, FPS_RULES_FILE) if use_optimized else None
        session_rows = ev.pedal_rows(table, table.meta.get("session_id", Path(path).name), truth,
                                     load_rules(rules_file) if rules_file else None)
        overall = ev.overall_pedal_row(session_rows)
        rows += session_rows + ([overall] if overall else [])
        tables.append(table)
        if plots:
            files += pedal_figures(path, table, truth, session_rows)
    per_pedal = ev.summarise(rows, ["pedal", "channel"], ["f1", "precision", "recall", "iou", "lag_ms", "usage_pct"])
    n = len({r["session"] for r in rows})
    result = EvalResult({"pedals": (per_pedal, f"Foot pedal state detection, averaged over {n} trial(s)")},
                        {"pedals": rows}, files, _provenance(paths, tables))
    result.files += write_tables(_default_out(paths, out), "pedals", result.tables, result.rows, result.provenance)
    return result


def pedal_figures(path: Path, table: AlignedTable, truth: dict[str, np.ndarray], rows: list[dict]) -> list[Path]:
    folder = output_dir(path, "plots")
    files = []
    for row in rows:
        if row["tp"] + row["fn"] == 0:
            continue
        det = ev.pedal_detection(table, row["pedal"])
        files.append(pedal_figure(table.times_s(), np.nan_to_num(truth[row["pedal"]]), np.nan_to_num(det),
                                  folder / f"pedal_{row['pedal']}.png",
                                  f"{row['pedal']} (FPS channel {row['channel']}): F1 {row['f1']:.2f}, IoU {row['iou']:.2f}"))
    return files


def optimise_pedals(paths: list[Path], out: Path | None) -> dict[str, Any]:
    """Per pedal, the threshold (V) and polarity maximising F1 over all frames of ``paths`` against the
    ground truth; reports F1 of the recorded states (before) and of the rule (after). Writes
    ``calib/fps_optimized.json`` into each session (or ``out``). Pedals never pressed are left out."""
    for path in paths:  # a folder that is no valid session gets nothing written into it
        Session.open(path)
    read = [file for p in paths for file in (*aligned_files(p), Path(p) / PEDALS_GT)]
    targets = [out_target(out, inputs=read)] if out else [calib_path(p, FPS_RULES_FILE) for p in paths]  # checked first
    volts: dict[str, list[np.ndarray]] = {}
    truths: dict[str, list[np.ndarray]] = {}
    before: dict[str, list[np.ndarray]] = {}
    for path in paths:
        table = read_aligned(path)
        for pedal, gt in ev.pedal_truth(table, read_pedals_ground_truth(path)).items():
            column = f"fps.ch{ev.PEDAL_CHANNELS[pedal]}_adc"
            if table.has(column):
                volts.setdefault(pedal, []).append(adc_to_volts(table.column(column)))
                truths.setdefault(pedal, []).append(gt)
                before.setdefault(pedal, []).append(ev.pedal_detection(table, pedal))
    pedals = {}
    for pedal in volts:
        v, g, b = (np.concatenate(x[pedal]) for x in (volts, truths, before))
        if not np.nansum(g):
            continue  # never pressed in the ground truth: nothing to optimise against
        rule, f1 = best_rule(v, g)
        pedals[pedal] = {"channel": ev.PEDAL_CHANNELS[pedal], "threshold_v": rule.threshold_v,
                         "polarity": rule.polarity, "f1_before": binary_scores(b, g).f1, "f1_after": f1}
    if not pedals:
        raise SessionError("no pedal is ever pressed in the ground truth of these sessions: nothing to optimise")
    document = json_safe({"format": "midas-fps-optimized-v1", "trained_on": [str(p) for p in paths], "pedals": pedals,
                          "rule": "pressed when volts >= threshold (above) or <= threshold (below); no hysteresis"})
    for target in targets:
        write_json(target, document)
    return {**document, "written": [str(t) for t in targets]}


def best_rule(volts: np.ndarray, truth: np.ndarray) -> tuple[ev.PedalRule, float]:
    """The (threshold, polarity) with the highest F1 over every distinct voltage as threshold (exact,
    O(n log n): frames sorted by voltage, true positives counted cumulatively)."""
    ok = np.isfinite(volts) & np.isfinite(truth)
    v, g = volts[ok], truth[ok] > 0.5
    if not g.any():
        raise SessionError("cannot optimise a pedal threshold without any pressed ground-truth frame")
    best = (ev.PedalRule(float(v.max())), -1.0)
    for polarity, sign in (("above", 1.0), ("below", -1.0)):
        order = np.argsort(-sign * v, kind="stable")  # most "pressed-like" first
        ranked, tp = v[order], np.cumsum(g[order])
        last = np.r_[ranked[1:] != ranked[:-1], True]  # threshold = ranked[i] takes every frame up to i
        f1 = np.where(last, 2 * tp / (np.arange(1, len(v) + 1) + g.sum()), -1.0)  # 2tp / (2tp + fp + fn)
        k = int(np.argmax(f1))
        if f1[k] > best[1]:
            best = (ev.PedalRule(float(ranked[k]), polarity), float(f1[k]))
    return best
