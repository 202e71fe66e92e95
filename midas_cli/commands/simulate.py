"""`midas simulate ...`: synthetic recordings with known ground truth (no hardware needed)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer

from midas_cli.commands import executor as ex
from midas_cli.commands.common import err, error_line, non_negative, out, positive, print_json
from midas_cli.commands.options import JSON_OPTION, renamed_option, take_renamed
from midas_cli.commands.progress import progress_display
from midas_cli.errors import ConfigError
from midas_cli.jobs.options import BatchOptions

app = typer.Typer(help="Synthetic recordings with known ground truth (no hardware needed).", no_args_is_help=True)


@app.command("dataset")
@ex.batch_command
def dataset(
    out_root: Path = typer.Option(..., "--out", help="Folder to create the session folders in."),
    platform: str = typer.Option("davinci-xi", "--platform", help="davinci-xi (suturing) or raven-ii (peg transfer)."),
    trials: int = typer.Option(3, "--trials", help="Number of trials (one session folder each)."),
    seed: int = typer.Option(0, "--seed", help="Seed: the same seed gives byte-identical sessions."),
    subjects: int = typer.Option(1, "--subjects", help="Subjects the trials are spread over."),
    latency_ms: float = typer.Option(40.0, "--latency-ms", callback=non_negative, help="True EmHT latency in ms."),
    distortion_mm: float = typer.Option(1.0, "--distortion-mm", callback=non_negative,
                                        help="Peak field distortion in mm (trakSTAR static accuracy is ~1.4 mm RMS)."),
    max_seconds: Optional[float] = typer.Option(None, "--max-seconds", callback=positive, help="Cut each trial to this length (s)."),
    difficulty: str = typer.Option("real", "--difficulty", help="real (subjects differ in speed, style and "
                                   "handedness; blended gestures, pauses, unlabelled stretches, sensor placement) "
                                   "or easy (every subject moves alike)."),
    emht_drift_ppm: float = typer.Option(0.0, "--emht-drift-ppm", help="The EmHT's host stamps drift by this "
                                         "much (ppm) against true time: its offset to the robot grows over the "
                                         "trial (what `midas eval sync` measures)."),
    as_json: bool = JSON_OPTION,
    *,
    batch: BatchOptions,
) -> None:
    """Write a simulated dataset with known ground truth, one session per trial.

    Write a simulated dataset: one complete session per trial with known ground truth (gesture
    labels, calibration truth and, on the da Vinci, derived/pedals_gt.csv).

    Example: midas simulate dataset --out sessions --platform davinci-xi --trials 4 --seed 1

    Example (one SLURM array task per trial): midas simulate dataset --out data/raven --platform raven-ii --trials 200 --executor slurm --run-dir runs/sim-raven
    """
    from midas_cli.simulate.dataset import trial_configs
    from midas_cli.simulate.dataset_units import TASK, plan_units

    choice = batch.choice()
    configs = trial_configs(platform, trials, seed, out_root, subjects, latency_ms, distortion_mm, max_seconds,
                           difficulty, emht_drift_ppm)
    outcome = ex.run_plan(TASK, plan_units(configs), choice, "simulating trials")
    if outcome.submitted:  # --no-wait: the run folder is printed
        return
    results: list[dict[str, Any]] = [r for r in outcome.results if r is not None]
    for result in results:
        err.print(f"midas: simulated {result['path']} ({result['duration_s']:.1f} s)", markup=False)
    if as_json:
        print_json(results)
    else:
        for result in results:
            out.print(result["path"], markup=False)
    outcome.raise_failed("trials")


@app.command("console-video")
def console_video(
    out_path: Path = typer.Option(..., "--out", help="Video file to write (.mkv/.mp4: mp4v, .avi: MJPG)."),
    duration: float = typer.Option(20.0, "--duration", callback=positive, help="Length in seconds."),
    seed: int = typer.Option(0, "--seed", help="Seed of the pedal schedule, picture and noise."),
    frame_rate: Optional[float] = typer.Option(None, "--frame-rate", callback=positive, help="Frame rate in Hz "
                                               "(default 30)."),
    old_fps: Optional[float] = renamed_option("--fps", "--frame-rate"),
    size: str = typer.Option("1920x1080", "--size", help="One view's WIDTHxHEIGHT in pixels."),
    stereo: bool = typer.Option(False, "--stereo", help="Side-by-side stereo (two views in one frame)."),
    noise: float = typer.Option(3.0, "--noise", callback=non_negative, help="Sensor noise, standard deviation in grey levels."),
    max_shift: int = typer.Option(1, "--max-shift", help="Largest whole-frame shift in pixels (capture jitter)."),
    layout: str = typer.Option("davinci-xi", "--layout", help="Layout whose indicators are drawn."),
    as_json: bool = JSON_OPTION,
) -> None:
    """Render a synthetic da Vinci Xi console video and its pedal schedule.

    Render a synthetic da Vinci Xi console video whose pedal indicators follow a seeded schedule,
    and write the schedule (frame, one 0/1 column per pedal) to <video stem>.schedule.csv beside
    it.

    Example: midas simulate console-video --out console.mkv --duration 20 --seed 1
    """
    from midas_cli.simulate.console_video import render_console_video
    from midas_cli.synthetic.console_video import ConsoleVideoSpec

    fps = take_renamed(frame_rate, old_fps, "--fps", "--frame-rate", error_line) or 30.0
    spec = ConsoleVideoSpec(duration, seed, fps, _parse_size(size), stereo, noise, max_shift, layout)
    with progress_display() as progress:
        task = progress.add_task("rendering frames", total=spec.frames)
        video = render_console_video(out_path, spec, lambda done, total: progress.update(task, completed=done))
    if as_json:
        print_json({"video": str(video.video), "schedule": str(video.schedule_csv), "frames": video.frames,
                    "pedals": video.pedals})
        return
    out.print(f"{video.frames} frames, pedals {', '.join(video.pedals)}", markup=False)
    out.print(str(video.schedule_csv), markup=False)
    out.print(str(video.video), markup=False)


def _parse_size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 1920x1080") from None
    return width, height
