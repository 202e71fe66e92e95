"""`midas import midas-dcs|jigsaws|compass`: other systems' recordings -> v1 session folders."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from midas_cli.commands.common import err, error_line, out, print_json
from midas_cli.commands.options import JSON_OPTION

app = typer.Typer(help="Import sessions from other formats.\n\n"
                       "Formats: original MiDAS folders, JIGSAWS, COMPASS.",
                  no_args_is_help=True)

FOLDER_ARG = typer.Argument(..., help="Source folder.")
OUT_OPTION = typer.Option(..., "--out", help="Folder that receives the new session folder(s).")


def _render(results: list[tuple[Path, dict[str, Any]]], as_json: bool) -> None:
    if as_json:
        print_json([{"path": str(path), "import_report": report} for path, report in results])
        return
    for path, report in results:
        err.print(_summary(report), markup=False, highlight=False)
        out.print(str(path), markup=False, highlight=False, soft_wrap=True)


def _summary(report: dict[str, Any]) -> str:
    """One line per source file (its name, then what was found and which quirks were handled), one line
    per discontinuity found in a file."""
    lines = [f"imported {report.get('source') or report.get('kinematics', {}).get('path')}"]
    keys = ("rows", "records", "frames", "header_quirk", "malformed_rows_skipped", "all_placeholder_rows",
            "host_times_adjusted", "note", "row_widths", "pds_block_placeholders")
    for name, facts in report.items():
        if isinstance(facts, dict) and "path" in facts:
            shown = [Path(facts["path"]).name] + [f"{k}={facts[k]}" for k in keys if k in facts]
            lines.append(f"  {name}: {', '.join(shown)}")
        elif isinstance(facts, str) and name != "source":
            lines.append(f"  {name}: {facts}")
    for item in report.get("discontinuities", []):
        lines.append(f"  discontinuity: {item['file']} line {item['line']}: {item['what']}")
    return "\n".join(lines)


@app.command("midas-dcs")
def midas_dcs(folder: Path = FOLDER_ARG, out_dir: Path = OUT_OPTION,
              platform: str = typer.Option("unknown", "--platform", help="Platform to record (not in the source)."),
              split: bool = typer.Option(False, "--split-recordings", help="A folder holding several recordings "
                                         "(host time going back, row shape changing mid-file) becomes one session "
                                         "per recording; without it such a folder is refused (exit 4)."),
              old_split: bool = typer.Option(False, "--split", hidden=True, help="Old name of --split-recordings."),
              as_json: bool = JSON_OPTION) -> None:
    """Import one folder of the original MiDAS system.

    Quirks and discontinuities (file, line, what) are reported here and in logs/import_report.json.

    Example: midas import midas-dcs ../shared/data/midas-dcs-sample/trakt_Strakt_T1_2024-07-05 --out sessions
    """
    from midas_cli.importers.midas_dcs import import_midas_dcs

    if old_split:  # `--split` is train's split strategy; here it was this flag's old name
        error_line("midas: warning: --split is now --split-recordings (the old name will go in a later release)")
    _render(import_midas_dcs(folder, out_dir, platform, split or old_split), as_json)


@app.command("jigsaws")
def jigsaws(folder: Path = FOLDER_ARG, out_dir: Path = OUT_OPTION, as_json: bool = JSON_OPTION) -> None:
    """Import every JIGSAWS trial under FOLDER.

    Reads kinematics/AllGestures/*.txt and transcriptions/*.txt.

    Example: midas import jigsaws JIGSAWS/Suturing --out sessions/jigsaws
    """
    from midas_cli.importers.surgical import import_surgical

    _render(import_surgical(folder, out_dir, "jigsaws"), as_json)


@app.command("compass")
def compass(folder: Path = FOLDER_ARG, out_dir: Path = OUT_OPTION, as_json: bool = JSON_OPTION) -> None:
    """Import every COMPASS trial under FOLDER.

    Reads kinematics/*.csv and gestures/*.txt.

    Example: midas import compass COMPASS/Datasets/dV/Suturing --out sessions/compass
    """
    from midas_cli.importers.surgical import import_surgical

    _render(import_surgical(folder, out_dir, "compass"), as_json)
