"""`midas extract image-features` as units of a batch run (midas_cli/jobs): one unit per video or session.

An input is a video file (features to ``--out``, or ``<video stem>.image_features.npz`` beside it) or a
session folder with one video in ``video/`` (features to ``derived/image_features.npz``, where
``midas train --modalities image`` reads them). A unit's fingerprint covers its options, the video's
and the weights' size and modification time, and the midas version.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable, Sequence

from midas_cli import __version__
from midas_cli.errors import SessionError
from midas_cli.jobs.rundir import Unit, fingerprint
from midas_cli.jobs.tasks import task_name
from midas_cli.models.image_features import ExtractOptions, extract_features
from midas_cli.session.pedals_gt import the_session_video

TASK = task_name(__name__)  # registered in jobs/tasks.py
SESSION_OUTPUT = Path("derived") / "image_features.npz"


def resolve(source: Path, out: Path | None) -> tuple[Path, Path]:
    """(video, output NPZ) of one input; SessionError for a session without exactly one video."""
    source = Path(source)
    if source.is_dir():
        return the_session_video(source), out or source / SESSION_OUTPUT
    return source, out or source.with_name(f"{source.stem}.image_features.npz")


def _stat(path: Path) -> Any:
    try:
        stat = path.stat()
    except OSError as exc:
        return str(exc)
    return [stat.st_size, stat.st_mtime_ns]


def plan_units(inputs: Sequence[Path], weights: Path, options: ExtractOptions, out: Path | None) -> list[Unit]:
    units = []
    for source in inputs:
        args = {"input": str(Path(source).resolve()), "weights": str(Path(weights).resolve()),
                "options": asdict(options), "out": str(Path(out).resolve()) if out else None}
        try:
            video = str(resolve(Path(args["input"]), None)[0])
        except SessionError as exc:  # the unit fails with this when it runs
            video = str(exc)
        units.append(Unit(Path(source).name, args,
                          fingerprint(TASK, args, _stat(Path(video)), _stat(Path(weights)), __version__)))
    return units


def run_unit(args: dict[str, Any], progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Encode one input's frames (a unit's ``args``); the summary (out, frames, dim, backbone)."""
    video, out = resolve(Path(args["input"]), Path(args["out"]) if args["out"] else None)
    summary = extract_features(video, Path(args["weights"]), ExtractOptions(**args["options"]), out, progress)
    return {"result": {"input": args["input"], **summary}, "outputs": [summary["out"]]}
