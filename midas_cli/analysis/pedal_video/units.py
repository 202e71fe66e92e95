"""`midas extract pedals` as units of a batch run (midas_cli/jobs): one unit per session or video.

A unit's fingerprint covers its request (input, layout, view, debouncing, output), the video's size
and modification time, the layout file's bytes (when the layout is a file) and the midas version.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable, Sequence

from midas_cli import __version__
from midas_cli.analysis.pedal_video.ground_truth import GroundTruthRequest, resolve_input, run_ground_truth
from midas_cli.errors import MidasError
from midas_cli.jobs.rundir import Unit, file_digest, fingerprint
from midas_cli.jobs.tasks import task_name

TASK = task_name(__name__)  # registered in jobs/tasks.py


def _inputs(request: GroundTruthRequest) -> Any:
    try:
        video, _, _ = resolve_input(request.input, request.out)
    except MidasError as exc:  # the unit fails when it runs, with this message
        return str(exc)
    stat = video.stat()
    layout = Path(request.layout)
    return {"video": (str(video), stat.st_size, stat.st_mtime_ns),
            "layout": file_digest(layout) if layout.is_file() else request.layout}


def plan_units(requests: Sequence[GroundTruthRequest]) -> list[Unit]:
    units = []
    for request in requests:
        args = {**asdict(request), "input": str(Path(request.input).resolve()),
                "out": str(Path(request.out).resolve()) if request.out is not None else None}
        units.append(Unit(Path(request.input).name, args, fingerprint(TASK, args, _inputs(request), __version__)))
    return units


def run_unit(args: dict[str, Any], progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Pedal ground truth of one input (a unit's ``args``); the result as `--json` prints it."""
    request = GroundTruthRequest(**{**args, "input": Path(args["input"]),
                                    "out": Path(args["out"]) if args["out"] else None})
    result = run_ground_truth(request, progress)
    return {"result": {"ok": True, **asdict(result), "speed_fps": round(result.speed_fps, 1)},
            "outputs": [result.csv, result.sidecar]}
