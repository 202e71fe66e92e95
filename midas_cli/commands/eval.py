"""`midas eval correlation|pedals|sync`: the paper's validation tables from aligned sessions, and the
measured offsets between modalities."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer
from rich.table import Table

from midas_cli.commands.common import err, out, print_json
from midas_cli.commands.options import ALIGNED_SESSIONS_ARG, JSON_OPTION

if TYPE_CHECKING:
    from midas_cli.analysis.eval_runs import EvalResult
    import pandas as pd

app = typer.Typer(help="Validate sensing modalities against robot ground truth (paper tables).",
                  no_args_is_help=True)

OUT_OPTION = typer.Option(None, "--out", help="Folder for the tables averaged over all sessions (CSV, JSON, "
                          "Markdown, LaTeX); default with one session: its derived/eval/.", file_okay=False)
PLOTS_OPTION = typer.Option(True, "--plots/--no-plots", help="Write PNG figures into each session's derived/plots/.")


@app.command()
def correlation(sessions: list[Path] = ALIGNED_SESSIONS_ARG, out_dir: Optional[Path] = OUT_OPTION,
                plots: bool = PLOTS_OPTION,
                model: str = typer.Option("best", "--calibration-model", help=(
                    "Calibration model of the main table: best (the one align recorded: calibrate's held-out "
                    "winner unless told otherwise), rigid or mlp. An MLP worse than the rigid fit on held-out "
                    "trials is marked mlp* wherever it is listed.")),
                as_json: bool = JSON_OPTION) -> None:
    """Agreement of EmHT and HandKP with the robot kinematics (CoS, NRMSE).

    CoS and NRMSE per axis (X, Y, Z, roll, pitch, yaw) for EmHT-MTM, EmHT-PSM, HandKP-MTM,
    HandKP-PSM, grasper open/close IoU/accuracy/precision, HandKP with and without missing frames,
    and the hand modalities' lag; averaged over the sessions (trials) and both hands.

    Example: midas eval correlation data/raven/*/ --out results/raven-ii
    """
    from midas_cli.analysis.eval_runs import run_correlation

    _render(run_correlation(sessions, out_dir, plots, lambda m: err.print(f"evaluating {m}", markup=False), model),
            as_json)


@app.command()
def pedals(sessions: list[Path] = ALIGNED_SESSIONS_ARG, out_dir: Optional[Path] = OUT_OPTION, plots: bool = PLOTS_OPTION,
           optimized: bool = typer.Option(False, "--optimized", help="Detect presses with the thresholds of "
                                          "`calibrate fps-optimize` (calib/fps_optimized.json) instead of the "
                                          "recorded states."),
           as_json: bool = JSON_OPTION) -> None:
    """Frame-level precision, recall, F1, IoU and lag of the FPS pedals.

    Per pedal and overall frame-level precision, recall, F1, temporal IoU and lag (ms) of the FPS
    against Raven-II clutch telemetry or derived/pedals_gt.csv, averaged over the sessions.

    Example: midas eval pedals data/davinci/*/ --out results/davinci-xi
    """
    from midas_cli.analysis.eval_runs import run_pedals

    _render(run_pedals(sessions, out_dir, plots, optimized, lambda m: err.print(f"evaluating {m}", markup=False)),
            as_json)


@app.command()
def sync(sessions: list[Path] = typer.Argument(..., help="Session folders (align not needed).", show_default=False),
         out_dir: Optional[Path] = typer.Option(None, "--out", file_okay=False, help="Folder for the table (CSV, "
                                                "JSON, Markdown, LaTeX); default with one session: its derived/eval/."),
         threshold_ms: float = typer.Option(5.0, "--threshold-ms", help="Largest offset (ms) between two "
                                            "modalities, overall and in any window, that is still ok."),
         windows: int = typer.Option(6, "--windows", help="Stretches of the session the motion offset is also "
                                     "measured in (their spread and slope give its uncertainty and drift)."),
         plots: bool = typer.Option(True, "--plots/--no-plots", help="Write derived/plots/sync.png per session."),
         as_json: bool = JSON_OPTION) -> None:
    """How late each modality sees what another sees too: the offsets between streams.

    From events two modalities both observe: hand motion in the EmHT and the robot kinematics (speed
    cross-correlation, over the session and in --windows stretches: spread and drift), pedal presses
    in the console video (derived/pedals_gt.csv) and on the pedal board. Offset = how late the second
    of the pair is (ms); a verdict against --threshold-ms. Exit 4 when a session has no such pair.

    Example: midas eval sync data/raven/*/ --out results/sync --threshold-ms 5
    """
    from midas_cli.analysis.sync_eval import run_sync

    pairs, files = run_sync(sessions, out_dir, threshold_ms, windows, plots,
                            lambda m: err.print(f"measuring {m}", markup=False))
    if as_json:
        print_json([p.to_json() for p in pairs])
    else:
        table = Table("session", "pair", "evidence", "offset ms", "spread ms", "drift ppm", "worst ms", "verdict",
                      title="Offsets between modalities (+ = the second is late)", header_style="bold")
        for p in pairs:
            table.add_row(p.session, p.pair, p.evidence, f"{p.offset_ms:.2f}", _num(p.spread_ms, ".2f"),
                          _num(p.drift_ppm, ".0f"), f"{p.worst_ms:.2f}", p.verdict)
        out.print(table)
    err.print(f"wrote {len(files)} file(s), e.g. {files[-1]}" if files else "wrote nothing", markup=False)


@app.command()
def live(sessions: list[Path] = typer.Argument(..., help="Sessions recorded with `midas record --live-model`.",
                                               show_default=False),
         run: Optional[Path] = typer.Option(None, "--run", help="The live model's run (default: the one the "
                                            "manifest names)."),
         label_set: str = typer.Option("gestures", "--labels", help="Label set to compare with, when the session "
                                       "has it."),
         as_json: bool = JSON_OPTION) -> None:
    """Gestures recognised while recording against the labels and the offline model.

    On the frames of each session's gestures_live stream, for the network's own class and the decoded
    one (the run's clean-up run live, what the screen showed): accuracy, edit score and, per segment of
    the reference, whether it was detected live and how long after its start (ms); each one's latency
    (the time it was known - frame time) beside.

    Example: midas eval live sessions/suturing_S1_T9_20261126T150000Z
    """
    from midas_cli.analysis.live_eval import evaluate_live

    results = [evaluate_live(session, run, label_set) for session in sessions]
    if as_json:
        print_json([result.to_json() for result in results])
        return
    table = Table("session", "live", "reference", "frames", "accuracy", "edit", "detected", "delay p50/p90 ms",
                  "latency p50/p99 ms", title="gestures recognised live", header_style="bold")
    for result in results:
        for a in result.agreements:
            latency = result.latency_ms[a.prediction]
            table.add_row(result.session, a.prediction, a.reference, str(a.frames), _num(a.accuracy, ".3f"),
                          _num(a.edit, ".1f"), f"{a.detected}/{a.segments}",
                          f"{_num(a.delay_ms['p50'], '.0f')}/{_num(a.delay_ms['p90'], '.0f')}",
                          f"{_num(latency['p50'], '.1f')}/{_num(latency['p99'], '.1f')}")
    out.print(table)


def _num(value: Optional[float], spec: str) -> str:
    return "—" if value is None else format(value, spec)


def _render(result: EvalResult, as_json: bool) -> None:
    from midas_cli.analysis.report import json_safe

    if as_json:
        print_json(json_safe({"provenance": result.provenance, "files": [str(f) for f in result.files],
                              "tables": {k: t.to_dict("records") for k, (t, _) in result.tables.items()}}))
        return
    for table, caption in result.tables.values():
        if not table.empty:
            out.print(_rich(table, f"{caption} — {result.provenance['data_label']}"))
    err.print(f"wrote {len(result.files)} file(s), e.g. {result.files[-1]}" if result.files else "wrote nothing",
              markup=False)


def _rich(frame: pd.DataFrame, title: str) -> Table:
    from midas_cli.analysis.report import format_cell

    table = Table(*map(str, frame.columns), title=title, header_style="bold")
    for row in frame.itertuples(index=False):
        table.add_row(*(format_cell(v) for v in row))
    return table
