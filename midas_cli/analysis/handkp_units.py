"""`midas extract handkp` as units of a batch run (midas_cli/jobs): one unit per session.

A unit's fingerprint covers its options and what extraction reads: every file under the session's
``video/`` and ``calib/`` (name, size, modification time) and the midas version; not the manifest,
which the extraction itself changes when it adds the stream.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

from midas_cli import __version__
from midas_cli.analysis.handkp import extract_handkp
from midas_cli.errors import ConfigError
from midas_cli.jobs.rundir import Unit, fingerprint
from midas_cli.jobs.tasks import task_name
from midas_cli.session.names import check_name

TASK = task_name(__name__)  # registered in jobs/tasks.py


def _recorded(session: Path) -> list[Any]:
    found = []
    for folder in ("video", "calib"):
        root = session / folder
        for path in sorted(root.rglob("*")) if root.is_dir() else []:
            if path.is_file():
                stat = path.stat()
                found.append([str(path.relative_to(session)), stat.st_size, stat.st_mtime_ns])
    return found


def plan_units(sessions: Sequence[Path], detector: str, device: str | None, stream: str, force: bool,
               mirrored: bool) -> list[Unit]:
    check_name(stream, "stream", "--stream", ConfigError)  # it names streams/<stream>.csv
    units = []
    for session in sessions:
        path = Path(session).resolve()
        args = {"session": str(path), "detector": detector, "device": device, "stream": stream, "force": force,
                "mirrored": mirrored}
        units.append(Unit(path.name, args, fingerprint(TASK, args, _recorded(path), __version__)))
    return units


def run_unit(args: dict[str, Any], progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Extract one session's HandKP stream (a unit's ``args``)."""
    result = extract_handkp(args["session"], args["detector"], args["device"], args["stream"], args["force"],
                            args["mirrored"], progress=progress)
    return {"result": result.to_json(), "outputs": [str(Path(args["session"]) / "streams" / f"{args['stream']}.csv")]}
