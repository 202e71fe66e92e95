"""`midas export`: sessions -> MCAP, Parquet, XDF files and/or LeRobot datasets in one output folder.

``<out>/<session_id>.mcap``, ``<out>/<session_id>/*.parquet``, ``<out>/<session_id>.xdf``,
``<out>/<session_id>.lerobot/`` (see each writer's module). Each file (the LeRobot dataset: its folder)
is written beside its target and renamed into place.

One entry per format (``EXPORT_FORMATS``): its ``--format`` name, what it writes per session and its
writer. Adding a format is one entry below plus its writer's module (and its sentence in `midas
export`'s help, which a test holds to this table). The writers import their module only when they
run, so this table is read for ``midas export --help`` without importing pyarrow, mcap or numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from midas_cli.errors import ConfigError
from midas_cli.session.outputs import out_child, out_child_folder, out_folder
from midas_cli.session.reader import Session

# A writer: (session, output folder, file stem = session id, with_video) -> what was written.
Writer = Callable[[Session, Path, str, bool], dict[str, Any]]


@dataclass(frozen=True)
class ExportFormat:
    """One export format: its ``--format`` ``name``, the ``target`` it writes per session (as the
    command's help names it) and its ``write`` (see :data:`Writer`)."""

    name: str
    target: str
    write: Writer


def _mcap(session: Session, folder: Path, stem: str, with_video: bool) -> dict[str, Any]:
    from midas_cli.interop.mcap_export import write_mcap

    return write_mcap(session, out_child(folder, f"{stem}.mcap"), with_video)


def _parquet(session: Session, folder: Path, stem: str, with_video: bool) -> dict[str, Any]:
    from midas_cli.interop.parquet_export import write_parquet

    return write_parquet(session, out_child_folder(folder, stem))


def _xdf(session: Session, folder: Path, stem: str, with_video: bool) -> dict[str, Any]:
    from midas_cli.interop.xdf import write_xdf

    return write_xdf(session, out_child(folder, f"{stem}.xdf"))


def _lerobot(session: Session, folder: Path, stem: str, with_video: bool) -> dict[str, Any]:
    from midas_cli.interop.lerobot_export import write_lerobot

    return write_lerobot(session, folder, f"{stem}.lerobot")


# In the order the formats are written and listed (the help's, the results').
EXPORT_FORMATS = (
    ExportFormat("mcap", "<out>/<id>.mcap", _mcap),
    ExportFormat("parquet", "<out>/<id>/<stream>.parquet", _parquet),
    ExportFormat("xdf", "<out>/<id>.xdf", _xdf),
    ExportFormat("lerobot", "<out>/<id>.lerobot/", _lerobot),
)
FORMATS = {entry.name: entry for entry in EXPORT_FORMATS}


def format_help() -> str:
    """The ``--format`` help: every format's name, in table order."""
    names = list(FORMATS)
    listed = f"{', '.join(names[:-1])} and/or {names[-1]}" if len(names) > 1 else names[0]
    return f"{listed} (repeat the option or separate with commas)."


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
    for name in formats:
        if progress is not None:
            progress(f"{session.path.name}: {name}")
        result[name] = FORMATS[name].write(session, folder, stem, with_video)
    return result
