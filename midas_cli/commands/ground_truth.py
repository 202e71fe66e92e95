"""`midas extract pedals`: pedal states read from the console video's UI indicators.

The `extract` group (commands/extract.py) registers ``pedals``; ``app`` here is its old spelling,
`midas ground-truth pedals`, kept for a release (hidden; commands/root.py's registry warns on use)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer
from rich.table import Table

from midas_cli.commands import executor as ex
from midas_cli.commands.common import err, out, print_json
from midas_cli.commands.options import JSON_OPTION
from midas_cli.errors import ConfigError
from midas_cli.jobs.options import BatchOptions

app = typer.Typer(help="Ground truth read from recordings (pedal states from the console video).",
                  no_args_is_help=True)

REAL_TIME_FPS = 30.0


@app.command("pedals")
@ex.batch_command
def pedals(
    inputs: list[Path] = typer.Argument(..., help="Session folders (one video in video/) or video files."),
    layout: str = typer.Option("davinci-xi", "--layout", help="Built-in layout name or a layout TOML file."),
    view: str = typer.Option("auto", "--view", help="auto (left half of side-by-side stereo), left or full."),
    min_duration: int = typer.Option(1, "--min-duration", help="Drop state changes lasting fewer frames."),
    preview: Optional[int] = typer.Option(None, "--preview", help="Frame index (0-based): draw the regions "
                                          "and their states on that frame instead of extracting."),
    out_path: Optional[Path] = typer.Option(None, "--out", help="PNG for --preview; CSV for one bare video "
                                            "(default: <video>.pedals_gt.csv beside it)."),
    as_json: bool = JSON_OPTION,
    *,
    batch: BatchOptions,
) -> None:
    """Read pedal states from the console video into derived/pedals_gt.csv.

    Read pedal states from the console video; write derived/pedals_gt.csv (frame = 0-based video
    frame index = seq of the session's video stream, t_host_ns, one 0/1 column per pedal) and a
    JSON sidecar.

    Example: midas extract pedals sessions/suturing_S1_T1_20260101T120000Z --min-duration 2
    """
    from midas_cli.analysis.pedal_video.ground_truth import GroundTruthRequest
    from midas_cli.analysis.pedal_video.layout import load_layout
    from midas_cli.analysis.pedal_video.units import TASK, plan_units

    if preview is not None:
        _preview(inputs, layout, view, preview, out_path, as_json)
        return
    choice = batch.choice()
    if out_path is not None and len(inputs) > 1:
        raise ConfigError("--out names one output file: give one video, or leave --out out")
    requests = [GroundTruthRequest(p, layout, view, min_duration, out_path) for p in inputs]
    load_layout(layout)  # a bad layout is one usage error, not one failure per input
    outcome = ex.run_plan(TASK, plan_units(requests), choice, "videos", ex.counted("frames"))
    if outcome.submitted:  # --no-wait: the run folder is printed
        return
    results = [{**r, "input": str(given)} if r else
               {"ok": False, "input": str(given), "message": next(f.error for f in outcome.failed if f.name == given.name)}
               for given, r in zip(inputs, outcome.results)]
    for r in results:
        if r["ok"]:
            err.print(f"midas: {r['input']}: {r['frames']} frames -> {r['csv']}", markup=False)
    if as_json:
        print_json(results)
    else:
        _render([r for r in results if r["ok"]])
    outcome.raise_failed("inputs")


def _preview(inputs: list[Path], layout: str, view: str, frame: int, out_path: Optional[Path], as_json: bool) -> None:
    from midas_cli.analysis.pedal_video.ground_truth import resolve_input
    from midas_cli.analysis.pedal_video.layout import load_layout
    from midas_cli.analysis.pedal_video.preview import preview_frame, write_png

    if len(inputs) != 1 or out_path is None:
        raise ConfigError("--preview needs exactly one session or video and --out FILE.png")
    video, _, _ = resolve_input(inputs[0], None)
    picture, reading = preview_frame(video, load_layout(layout), frame, view)
    path = write_png(out_path, picture)
    if as_json:
        print_json({"png": str(path), "frame": frame, "pedals": reading.pedals,
                    "regions": {k: {"on": s, "score": round(v, 4)} for k, (s, v) in reading.regions.items()}})
        return
    pressed = [p for p, on in reading.pedals.items() if on]
    out.print(f"frame {frame}: pressed {', '.join(pressed) or 'none'}", markup=False)
    out.print(str(path), markup=False)


def _render(results: list[dict[str, Any]]) -> None:
    if not results:
        return
    pedals = list(results[0]["pressed_fraction"])
    table = Table("input", "frames", "processed frames/s", "x real time", *[f"{p} %" for p in pedals], "output", header_style="bold")
    for r in results:
        table.add_row(Path(r["input"]).name, str(r["frames"]), f"{r['speed_fps']:.0f}",
                      f"{r['speed_fps'] / REAL_TIME_FPS:.1f}",
                      *[f"{100 * r['pressed_fraction'].get(p, 0):.1f}" for p in pedals], r["csv"])
    out.print(table)
