"""`midas extract ...`: offline steps that derive data from what a session recorded.

`extract handkp` lives here; `extract pedals` (commands/ground_truth.py) and `extract image-features`
(commands/features.py) are registered from their modules, which also serve their old spellings
(`ground-truth pedals`, `features image`) for a release."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from midas_cli.commands import executor as ex
from midas_cli.commands.common import out
from midas_cli.commands.features import image as image_features
from midas_cli.commands.ground_truth import pedals
from midas_cli.commands.options import JSON_OPTION
from midas_cli.jobs.options import BatchOptions

app = typer.Typer(help="Derive data from recordings offline: hand keypoints, pedals, image features.",
                  no_args_is_help=True)


@app.command()
@ex.batch_command
def handkp(
    sessions: list[Path] = typer.Argument(..., help="Session(s) recorded with a stereo camera (uvc://, zed://, "
                                          "sim://rgbd).", file_okay=False),
    detector: str = typer.Option("mediapipe", "--detector", help="mediapipe, or truth (simulated sessions only)."),
    device: Optional[str] = typer.Option(None, "--device", help="The stereo camera device, if there are several."),
    stream: str = typer.Option("handkp", "--stream", help="Name of the HandKP stream to add."),
    force: bool = typer.Option(False, "--force", help="Replace a HandKP stream an earlier extraction added."),
    mirrored: bool = typer.Option(False, "--mirrored", help="The camera image is mirrored (MediaPipe handedness)."),
    as_json: bool = JSON_OPTION,
    *,
    batch: BatchOptions,
) -> None:
    """Detect fingertips in the stereo frames and add the HandKP stream.

    Detect thumb and middle fingertips of both hands in every recorded stereo frame, give them 3-D
    positions in the camera frame (mm) from StereoSGBM depth with the session's calibration, and
    add the HandKP stream to the session (missed hands are empty fields, never zeros).

    Example: midas extract handkp sessions/suturing_S1_T1_20250101T120000Z --detector mediapipe

    Example (one SLURM array task per session): midas extract handkp data/*/ --executor slurm --slurm-time 01:00:00 --run-dir runs/handkp
    """
    from midas_cli.analysis.handkp_units import TASK, plan_units

    choice = batch.choice()
    units = plan_units(sessions, detector, device, stream, force, mirrored)
    outcome = ex.run_plan(TASK, units, choice, "sessions", ex.counted("extracting hand keypoints"))
    if outcome.submitted:  # --no-wait: the run folder is printed
        return
    for result in ex.shown_results(outcome, as_json, single=len(sessions) == 1):
        out.print(f"{result['stream']}: {result['frames']} frames from {result['device']}, hands detected left "
                  f"{result['detected']['left']} right {result['detected']['right']}, "
                  f"{result['keypoints_with_depth']} fingertips with depth", markup=False, highlight=False)
    outcome.raise_failed("sessions")


app.command("pedals")(pedals)
app.command("image-features")(image_features)
