"""`midas extract ...`: offline steps that derive streams from what a session recorded."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from midas_cli.commands.common import out, print_json
from midas_cli.commands.options import JSON_OPTION
from midas_cli.commands.progress import progress_display

app = typer.Typer(help="Derive streams from recorded data (offline).", no_args_is_help=True)


@app.command()
def handkp(
    session: Path = typer.Argument(..., help="Session recorded with a stereo camera (uvc://, zed://, sim://rgbd)."),
    detector: str = typer.Option("mediapipe", "--detector", help="mediapipe, or truth (simulated sessions only)."),
    device: Optional[str] = typer.Option(None, "--device", help="The stereo camera device, if there are several."),
    stream: str = typer.Option("handkp", "--stream", help="Name of the HandKP stream to add."),
    force: bool = typer.Option(False, "--force", help="Replace a HandKP stream an earlier extraction added."),
    mirrored: bool = typer.Option(False, "--mirrored", help="The camera image is mirrored (MediaPipe handedness)."),
    as_json: bool = JSON_OPTION,
) -> None:
    """Detect fingertips in the stereo frames and add the HandKP stream.

    Detect thumb and middle fingertips of both hands in every recorded stereo frame, give them 3-D
    positions in the camera frame (mm) from StereoSGBM depth with the session's calibration, and
    add the HandKP stream to the session (missed hands are empty fields, never zeros).

    Example: midas extract handkp sessions/suturing_S1_T1_20250101T120000Z --detector mediapipe
    """
    from midas_cli.devices.rgbd.handkp import extract_handkp

    with progress_display(transient=True) as bar:
        task = bar.add_task("extracting hand keypoints", total=None)
        result = extract_handkp(session, detector, device, stream, force, mirrored,
                                progress=lambda done, total: bar.update(task, completed=done, total=total))
    if as_json:
        print_json(result.to_json())
        return
    out.print(f"{result.stream}: {result.frames} frames from {result.device}, hands detected left "
              f"{result.detected['left']} right {result.detected['right']}, {result.keypoints_with_depth} "
              f"fingertips with depth", markup=False, highlight=False)
