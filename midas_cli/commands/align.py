"""`midas align SESSION...`: every stream onto the video frame clock -> derived/aligned.* (npz, values.npy, json; + csv)."""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any, Optional

import typer
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from midas_cli.analysis.align import METHODS, AlignOptions, align_and_write, parse_clock
from midas_cli.commands.common import err, error_line, out, positive, print_json
from midas_cli.commands.options import JSON_OPTION, SESSIONS_ARG, renamed_option, take_renamed
from midas_cli.commands.progress import progress_display
from midas_cli.errors import ConfigError


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
    model: str = typer.Option("best", "--calibration-model", help="Calibration model to use downstream (eval): "
                              "best (the winner of calibrate's held-out comparison), rigid or mlp. Both models' "
                              "columns are written; the choice is recorded in derived/aligned.json."),
    jobs: int = typer.Option(1, "--jobs", "-j", help="Sessions aligned in parallel (worker processes)."),
    csv: bool = typer.Option(False, "--csv", help="Also write derived/aligned.csv (6 significant digits; "
                             "slow for long sessions: the npz holds the exact values). Without it, an "
                             "aligned.csv left by an earlier run is removed."),
    as_json: bool = JSON_OPTION,
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
    """
    if jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {jobs}")
    downsample = take_renamed(downsample, rate, "--rate", "--downsample", error_line)
    options = AlignOptions(method=method, rate_hz=downsample, clock_hz=parse_clock(clock), model=model)
    results = _run(sessions, options, jobs, csv)
    for r in results:
        for warning in r["warnings"]:
            err.print(f"midas: warning: {r['session']}: {warning}", markup=False, highlight=False, soft_wrap=True)
    if as_json:
        print_json(results)
        return
    table = Table("session", "frames", "columns", "masked (per stream)", "calibrations", header_style="bold")
    for r in results:
        masked = ", ".join(f"{k} {v:.1%}" for k, v in r["masked_fraction"].items())
        table.add_row(Path(r["session"]).name, str(r["frames"]), str(r["columns"]), masked,
                      ", ".join(f"{Path(c).stem} ({m})" for c, m in r["calibration_models"].items()) or "—")
    out.print(table)


def _run(sessions: list[Path], options: AlignOptions, jobs: int, csv: bool) -> list[dict[str, Any]]:
    """Align each session (in ``jobs`` processes), with a progress bar on stderr; input order kept."""
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TimeRemainingColumn())
    results: dict[Path, dict[str, Any]] = {}
    with progress_display(*columns, transient=True) as progress:
        task = progress.add_task("aligning sessions", total=len(sessions))
        if jobs == 1:
            for path in sessions:
                results[path] = align_and_write(path, options, csv)
                progress.advance(task)
        else:
            with ProcessPoolExecutor(max_workers=jobs) as pool:
                futures = {pool.submit(align_and_write, path, options, csv): path for path in sessions}
                for future in as_completed(futures):
                    results[futures[future]] = future.result()
                    progress.advance(task)
    return [results[p] for p in sessions]
