"""`midas calibrate emht|handkp|fps-optimize`: calibrations fitted on recorded sessions (the commands
are registered on the `calibrate` sub-app defined in calibrate.py)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

import typer
from rich.table import Table

from midas_cli.analysis.calibration import TARGETS
from midas_cli.commands.common import err, error_line, non_negative, out, print_json
from midas_cli.commands.options import JSON_OPTION, KINEMATIC_SESSIONS_ARG
from midas_cli.errors import ConfigError

if TYPE_CHECKING:
    from midas_cli.analysis.fit_calibration import CalibrationOptions

TARGET_OPTION = typer.Option("mtm", "--target", help=f"Robot frame to map into: {' or '.join(TARGETS)}.")
OUT_OPTION = typer.Option(None, "--out", help="Also write the model fitted on ALL sessions to this .json "
                          "(weights beside it as .pt).", dir_okay=False)
EPOCHS_OPTION = typer.Option(50, "--epochs", help="MLP training epochs (paper: 50).")
DECAY_OPTION = typer.Option(1.5, "--weight-decay", callback=non_negative, help="MLP L2 weight decay (paper: 1.5).")


def _options(target: str, rigid_only: bool, epochs: int, weight_decay: float) -> CalibrationOptions:
    from midas_cli.analysis.fit_calibration import CalibrationOptions
    from midas_cli.models.mlp_config import MLPConfig

    if target not in TARGETS:
        raise ConfigError(f"--target {target!r} is unknown (expected one of {', '.join(TARGETS)})")
    if epochs < 1:
        raise ConfigError(f"--epochs must be >= 1, got {epochs}")
    return CalibrationOptions(rigid_only=rigid_only, mlp=MLPConfig(epochs=epochs, weight_decay=weight_decay))


def emht(
    sessions: list[Path] = KINEMATIC_SESSIONS_ARG,
    target: str = TARGET_OPTION,
    rigid_only: bool = typer.Option(False, "--rigid-only", help="Fit R, t only (no residual MLP)."),
    out_file: Optional[Path] = OUT_OPTION,
    epochs: int = EPOCHS_OPTION,
    weight_decay: float = DECAY_OPTION,
    as_json: bool = JSON_OPTION,
) -> None:
    """Calibrate EmHT -> MTM/PSM: rigid fit plus residual MLP, per trial fold.

    EmHT -> MTM/PSM: rigid least-squares fit (Kabsch; Umeyama scale for PSM) + residual MLP (paper
    Appendix A.2), orientations by composition of rotations, EmHT latency estimated and
    compensated; leave-one-trial-out cross-validation. Each session's calib/ gets the fold model
    that did not see it; `midas align` applies it.

    Example: midas calibrate emht data/raven/*/ --target mtm --out results/emht_to_mtm.json
    """
    from midas_cli.analysis.fit_calibration import calibrate_sessions

    options = _options(target, rigid_only, epochs, weight_decay)
    report = calibrate_sessions(sessions, "emht", target, options, out_file, lambda m: err.print(m, markup=False))
    _render(report, as_json)


def handkp(
    sessions: list[Path] = KINEMATIC_SESSIONS_ARG,
    target: str = TARGET_OPTION,
    rigid_only: bool = typer.Option(False, "--rigid-only", help="Hand-eye rigid fit only (no direct MLP)."),
    out_file: Optional[Path] = OUT_OPTION,
    epochs: int = EPOCHS_OPTION,
    weight_decay: float = DECAY_OPTION,
    as_json: bool = JSON_OPTION,
) -> None:
    """Calibrate the HandKP camera -> MTM/PSM: hand-eye fit or direct MLP.

    HandKP camera -> MTM/PSM (paper Appendix A.3): rigid hand-eye fit of the keypoint midpoints,
    and the direct camera -> robot MLP alternative, on detected frames, leave-one-trial-out.

    Example: midas calibrate handkp data/raven/*/ --target mtm
    """
    from midas_cli.analysis.fit_calibration import calibrate_sessions

    options = _options(target, rigid_only, epochs, weight_decay)
    report = calibrate_sessions(sessions, "handkp", target, options, out_file, lambda m: err.print(m, markup=False))
    _render(report, as_json)


def _warn_if_mlp_worse(report: dict[str, Any]) -> None:
    """One stderr line when the MLP lost to the rigid fit on held-out trials (e.g. collapsed to a constant)."""
    selection = report["selection"]
    if selection.get("mlp_worse_than_rigid"):
        rigid, mlp = selection["held_out"]["rigid"], selection["held_out"]["mlp"]
        error_line(f"midas: warning: {report['source']} -> {report['target']}: the MLP is worse than the rigid "
                   f"fit on held-out trials (mean RMSE {mlp['rmse_mm']:.2f} mm vs {rigid['rmse_mm']:.2f} mm, "
                   f"CoS {mlp['cos']:.3f} vs {rigid['cos']:.3f}, {selection['folds']} folds); align and eval use "
                   f"the rigid fit (--calibration-model best; --calibration-model mlp to use it anyway)")


def _render(report: dict[str, Any], as_json: bool) -> None:
    _warn_if_mlp_worse(report)
    if as_json:
        print_json(report)
        return
    out.print(f"{report['source']} -> {report['target']}: {report['sessions']} session(s), lag "
              f"{report['lag_ms']:.1f} ms, scale {report['rigid']['scale']:.4f}, models {', '.join(report['models'])} "
              f"(align/eval use {report['selection']['best']}: {report['selection']['reason']})",
              markup=False)
    table = Table("held-out session", "lag ms", *[f"{m} RMSE mm" for m in report["models"]],
                  *[f"{m} CoS x/y/z" for m in report["models"]], "orient. err deg",
                  title="leave-one-trial-out cross-validation", header_style="bold")
    for fold in report["folds"]:
        rmse = [f"{fold[m]['rmse_mm']:.2f}" for m in report["models"]]
        cos = ["/".join(f"{fold[m][f'cos_{a}']:.3f}" for a in "xyz") for m in report["models"]]
        orient = fold.get("orientation_error_deg")
        table.add_row(fold["session"], f"{fold['lag_ms']:.1f}", *rmse, *cos, "—" if orient is None else f"{orient:.2f}")
    if report["folds"]:
        out.print(table)
    else:
        err.print("one session: no cross-validation (the calibration is fitted on it)", markup=False)
    for files in report["written"].values():
        err.print(f"wrote {', '.join(files)}", markup=False)


def fps_optimize(
    sessions: list[Path] = typer.Argument(..., help="Aligned session folder(s) with pedal ground truth.",
                                          file_okay=False),
    out_file: Optional[Path] = typer.Option(None, "--out", help="Write the thresholds here instead of into each "
                                            "session's calib/fps_optimized.json.", dir_okay=False),
    as_json: bool = JSON_OPTION,
) -> None:
    """Per pedal, the FSR threshold and polarity that maximise frame-level F1.

    Per pedal, the FSR voltage threshold and polarity that maximise frame-level F1 against the
    ground truth (Raven-II clutch telemetry or derived/pedals_gt.csv) over all given sessions, with
    F1 before (the recorded pressed states) and after. `midas eval pedals --optimized` uses the
    result.

    Example: midas calibrate fps-optimize data/davinci/*/ && midas eval pedals data/davinci/*/ --optimized --out results/pedals
    """
    from midas_cli.analysis.eval_runs import optimise_pedals

    report = optimise_pedals(sessions, out_file)
    if as_json:
        print_json(report)
        return
    table = Table("pedal", "FPS channel", "threshold V", "polarity", "F1 before", "F1 after", header_style="bold",
                  title="F1-optimal pedal thresholds")
    for pedal, r in report["pedals"].items():
        before = "—" if r["f1_before"] is None else f"{r['f1_before']:.3f}"
        table.add_row(pedal, str(r["channel"]), f"{r['threshold_v']:.3f}", r["polarity"], before, f"{r['f1_after']:.3f}")
    out.print(table)
    err.print(f"wrote {', '.join(report['written'])}", markup=False)
