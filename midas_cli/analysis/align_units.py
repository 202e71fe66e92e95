"""`midas align` as units of a batch run (midas_cli/jobs): one unit per session.

A unit's fingerprint covers what ``align_and_write`` reads and how: the manifest's bytes (stream
hashes of a finished session), each stream and binary copy's size and modification time, the bytes of
every file in ``calib/``, the alignment options, ``--csv`` and the midas version. A session recorded
again, recalibrated or aligned with other options is aligned again; anything else is skipped.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any, Sequence

from midas_cli import __version__
from midas_cli.analysis.align import AlignOptions, align_and_write
from midas_cli.jobs.rundir import Unit, file_digest, fingerprint
from midas_cli.jobs.tasks import task_name

TASK = task_name(__name__)  # registered in jobs/tasks.py


def session_inputs(session: Path) -> dict[str, Any]:
    """What of ``session`` alignment reads, summarised (digests, sizes, mtimes)."""
    session = Path(session)
    streams = {}
    for path in sorted((session / "streams").glob("*")) if (session / "streams").is_dir() else []:
        stat = path.stat()
        streams[path.name] = (stat.st_size, stat.st_mtime_ns)
    calib = {p.name: file_digest(p) for p in sorted((session / "calib").rglob("*")) if p.is_file()} \
        if (session / "calib").is_dir() else {}
    return {"manifest": file_digest(session / "manifest.json"), "streams": streams, "calib": calib}


def plan_units(sessions: Sequence[Path], options: AlignOptions, csv: bool) -> list[Unit]:
    units = []
    for session in sessions:
        path = str(Path(session).resolve())
        args = {"session": path, "options": asdict(options), "csv": csv}
        units.append(Unit(Path(path).name, args, fingerprint(TASK, args, session_inputs(Path(path)), __version__)))
    return units


def run_unit(args: dict[str, Any]) -> dict[str, Any]:
    """Align one session (a unit's ``args``); its summary and the files written."""
    result = align_and_write(Path(args["session"]), AlignOptions(**args["options"]), bool(args["csv"]))
    return {"result": result, "outputs": list(result["files"].values())}
