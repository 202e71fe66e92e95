"""`midas align SESSION...`: every stream onto the video frame clock -> derived/aligned.* (npz, values.npy, json; + csv)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from midas_cli.analysis.align import METHODS, AlignOptions, parse_clock
from midas_cli.commands import executor as ex
from midas_cli.commands.common import err, error_line, out, positive, print_json
from midas_cli.commands.options import JSON_OPTION, SESSIONS_ARG, renamed_option, take_renamed
from midas_cli.jobs.options import BatchOptions


@ex.batch_command
def align(
    sessions: list[Path] = SESSIONS_ARG,
    method: str = typer.Option("causal", "--method", help=f"Sample chosen per frame: {' or '.join(METHODS)} "
                               "(latest at or before the frame / nearest in time)."),
    downsample: Optional[float] = typer.Option(None, "--downsample", callback=positive, help="Keep one frame per "
                                               "1/HZ of the frame clock, e.g. 10; default: every frame."),
    rate: Optional[float] = renamed_option("--rate", "--downsample"),
    clock: str = typer.Option("video", "--clock", help="Reference clock: 'video' (the video frame times) or a "
                              "rate in Hz, e.g. 30: a regular clock spanning every stream's samples, for a "
                              "session whose video clock is short or absent."),
    times: str = typer.Option("host", "--times", help="Sample times used: host (the stamps as recorded) or fitted "
                              "(each stream's stamps fitted against its device clock: jitter removed; the fit's "
                              "drift and jitter are in derived/aligned.json either way)."),
    model: str = typer.Option("best", "--calibration-model", help="Calibration model to use downstream (eval): "
                              "best (the winner of calibrate's held-out comparison), rigid or mlp. Both models' "
                              "columns are written; the choice is recorded in derived/aligned.json."),
    csv: bool = typer.Option(False, "--csv", help="Also write derived/aligned.csv (6 significant digits; "
                             "slow for long sessions: the npz holds the exact values). Without it, an "
                             "aligned.csv left by an earlier run is removed."),
    as_json: bool = JSON_OPTION,
    *,
    batch: BatchOptions,
) -> None:
    """Align each session's streams onto its video frame clock.

    Align every stream of each session onto its video frame clock (causal or nearest sample,
    per-stream delta, HandKP gaps filled, masks instead of sentinels, calibrations in calib/
    applied, velocity / grasper distance / clutch derived) and write derived/aligned.npz,
    .values.npy and .json (and .csv with --csv). Streams are read from their binary copies
    (streams/*.npy) when they match the CSVs.

    Each stream's coverage by the clock (share of its samples and of its time span inside the first
    to last frame) is in the output and in derived/aligned.json; under 95% gets a warning on
    stderr.

    Example: midas align sessions/*/ --downsample 10 --jobs 2

    Example (a watch-only session, or a video clock covering a fraction): midas align SESSION --clock 30

    Example (one SLURM array task per session; a re-run skips the sessions done): midas align data/*/ --executor slurm --slurm-time 00:20:00 --run-dir runs/align
    """
    from midas_cli.analysis.align_units import TASK, plan_units

    choice = batch.choice()
    downsample = take_renamed(downsample, rate, "--rate", "--downsample", error_line)
    options = AlignOptions(method=method, rate_hz=downsample, clock_hz=parse_clock(clock), model=model, times=times)
    outcome = ex.run_plan(TASK, plan_units(sessions, options, csv), choice, "aligning sessions")
    if outcome.submitted:  # --no-wait: the run folder is printed
        return
    results = [{**r, "session": str(given)} for given, r in zip(sessions, outcome.results) if r is not None]
    for r in results:
        for warning in r["warnings"]:
            err.print(f"midas: warning: {r['session']}: {warning}", markup=False, highlight=False, soft_wrap=True)
    if as_json:
        print_json(results)
        outcome.raise_failed("sessions")
        return
    table = Table("session", "frames", "columns", "masked (per stream)", "calibrations", header_style="bold")
    for r in results:
        masked = ", ".join(f"{k} {v:.1%}" for k, v in r["masked_fraction"].items())
        table.add_row(Path(r["session"]).name, str(r["frames"]), str(r["columns"]), masked,
                      ", ".join(f"{Path(c).stem} ({m})" for c, m in r["calibration_models"].items()) or "—")
    if results:
        out.print(table)
    outcome.raise_failed("sessions")

