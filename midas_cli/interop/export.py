"""`midas export`: sessions -> MCAP, Parquet, XDF files and/or LeRobot datasets in one output folder.

``<out>/<session_id>.mcap``, ``<out>/<session_id>/*.parquet``, ``<out>/<session_id>.xdf``,
``<out>/<session_id>.lerobot/`` (see each writer's module). Each file (the LeRobot dataset: its folder)
is written beside its target and renamed into place.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

from midas_cli.errors import ConfigError
from midas_cli.interop.lerobot_export import write_lerobot
from midas_cli.interop.mcap_export import write_mcap
from midas_cli.interop.parquet_export import write_parquet
from midas_cli.interop.xdf import write_xdf
from midas_cli.session.outputs import out_child, out_child_folder, out_folder
from midas_cli.session.reader import Session

FORMATS = ("mcap", "parquet", "xdf", "lerobot")


def parse_formats(values: Sequence[str]) -> list[str]:
    """``--format`` values (repeatable, or comma-separated) in FORMATS order; ConfigError for another."""
    wanted = {v.strip().lower() for value in values for v in value.split(",") if v.strip()}
    unknown = sorted(wanted - set(FORMATS))
    if unknown or not wanted:
        raise ConfigError(f"--format {','.join(unknown) or '(none)'}: expected one or more of {', '.join(FORMATS)}")
    return [f for f in FORMATS if f in wanted]


def export_session(path: Path | str, formats: Sequence[str], out_dir: Path | str,
                   progress: Callable[[str], None] | None = None, with_video: bool = False) -> dict[str, Any]:
    """Export one session; returns what was written per format (``with_video``: images in the MCAP)."""
    session = Session.open(path)
    folder = out_folder(out_dir)
    stem = session.manifest["session_id"]  # checked by the manifest's validation; out_child checks again
    result: dict[str, Any] = {"session": str(session.path)}
    writers = {"mcap": lambda: write_mcap(session, out_child(folder, f"{stem}.mcap"), with_video),
               "parquet": lambda: write_parquet(session, out_child_folder(folder, stem)),
               "xdf": lambda: write_xdf(session, out_child(folder, f"{stem}.xdf")),
               "lerobot": lambda: write_lerobot(session, folder, f"{stem}.lerobot")}
    for name in formats:
        if progress is not None:
            progress(f"{session.path.name}: {name}")
        result[name] = writers[name]()
    return result
