"""`midas labels taxonomy|import-via|import-transcription|export|stats`: gesture annotations."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Optional

import typer
from rich.table import Table

from midas_cli.commands.common import err, error_line, out, positive, print_json
from midas_cli.errors import ConfigError
from midas_cli.commands.options import JSON_OPTION, SESSION_ARG, renamed_option, take_renamed
from midas_cli.labels.sessions import EXPORT_FORMATS, ImportOptions, ImportResult, export_labels, import_transcription
from midas_cli.labels.sessions import import_via as import_via_file
from midas_cli.labels.sessions import load_recordings
from midas_cli.labels.stats import GestureStats, gesture_stats, transition_heatmap
from midas_cli.labels.taxonomy import Taxonomy, list_taxonomies, load_taxonomy, shipped_taxonomy
from midas_cli.labels.transcription import JIGSAWS_FPS
from midas_cli.session.labels import label_set_files
from midas_cli.session.outputs import out_target, write_text

app = typer.Typer(help="Gesture taxonomies, annotation import/export and label statistics.\n\n"
                       "Annotation formats: VIA, JIGSAWS/COMPASS.",
                  no_args_is_help=True)

NAME_OPTION = typer.Option("gestures", "--name", help="Label set name (labels/<name>.csv in the session).")
GAPS_OPTION = typer.Option("unlabelled", "--gaps", help="Frames no segment covers: 'unlabelled' (empty label) "
                           "or 'idle' (the taxonomy's idle class, e.g. peg-transfer's Idle).")
OVERLAP_OPTION = typer.Option("later", "--overlap", help="Frames claimed by two segments go to the 'later' or "
                              "'earlier' starting one; 'error' refuses the file.")
FORCE_OPTION = typer.Option(False, "--force", help="Replace an existing label set of the same name.")
MAX_LISTED = 20
_SIDES = {"start": "at its start", "end": "at its end", "both": "at both ends"}


@app.command()
def taxonomy(name: Optional[str] = typer.Argument(None, help="Taxonomy name or .toml path; omit to list them."),
             as_json: bool = JSON_OPTION) -> None:
    """Print a gesture taxonomy as a table, or list the shipped taxonomies.

    Example: midas labels taxonomy hernia-suturing
    """
    if name is None:
        shipped = [load_taxonomy(n) for n in list_taxonomies()]
        if as_json:
            print_json([{"name": t.name, "title": t.title, "gestures": len(t.gestures)} for t in shipped])
            return
        table = Table("name", "title", "classes", header_style="bold")
        for t in shipped:
            table.add_row(t.name, t.title, str(len(t.gestures)))
        out.print(table)
        return
    tax = load_taxonomy(name)
    if as_json:
        print_json(tax.to_json())
        return
    _print_taxonomy(tax)


def _print_taxonomy(tax: Taxonomy) -> None:
    arms = any(g.main_arm or g.support_arm for g in tax.gestures)
    columns = ["ID", "Gesture", "Goal", "Main arm", "Support arm"] if arms else ["ID", "Gesture", "Description"]
    table = Table(*columns, title=f"{tax.name}: {tax.title}", header_style="bold", show_lines=arms)
    for g in tax.gestures:
        cells = [g.goal, g.main_arm, g.support_arm] if arms else [g.description]
        table.add_row(g.id, g.name, *cells)
    out.print(table)
    out.print(f"source: {tax.source}" + (f"; idle class: {tax.idle}" if tax.idle else ""), markup=False)


@app.command("import-via")
def import_via(
    export: Path = typer.Argument(..., help="VIA 3 project JSON or VIA 3 CSV export."),
    session: Path = SESSION_ARG,
    taxonomy_name: str = typer.Option(..., "--taxonomy", help="Taxonomy name or .toml path."),
    gaps: str = GAPS_OPTION,
    overlap: str = OVERLAP_OPTION,
    name: str = NAME_OPTION,
    force: bool = FORCE_OPTION,
    attribute: Optional[str] = typer.Option(None, help="VIA attribute (id or name) holding the gesture, when "
                                            "the file has several temporal attributes."),
    video_file: Optional[str] = typer.Option(None, help="Video file name to take, when the VIA file annotates several."),
    annotator: Optional[str] = typer.Option(None, help="Annotator name for the provenance (else read from the file)."),
    as_json: bool = JSON_OPTION,
) -> None:
    """Import VIA video-annotator segments as a session's frame labels.

    Turn VIA video-annotator segments (seconds) into frame labels on the session's video frames:
    frame i covers [i/fps, (i+1)/fps) and takes a segment's label when its midpoint lies inside it.
    Overlaps, gaps, segments past the video and skipped entries are reported.

    Example: midas labels import-via trial3_export.csv sessions/suturing_S1_T3_20260101T120000Z --taxonomy hernia-suturing
    """
    options = ImportOptions(taxonomy_name, gaps, overlap, name, force)
    _report(import_via_file(export, session, options, attribute, video_file, annotator), as_json)


@app.command("import-transcription")
def import_transcription_cmd(
    file: Path = typer.Argument(..., help="Transcription file: 'start end Gk' lines."),
    session: Path = SESSION_ARG,
    taxonomy_name: str = typer.Option("jigsaws-suturing", "--taxonomy", help="Taxonomy name or .toml path."),
    index_base: int = typer.Option(1, "--index-base", help="Number of the first frame in the file "
                                   "(JIGSAWS/COMPASS: 1, so line '80 219 G1' labels 0-based frames 79..218)."),
    gaps: str = GAPS_OPTION,
    overlap: str = OVERLAP_OPTION,
    name: str = NAME_OPTION,
    force: bool = FORCE_OPTION,
    as_json: bool = JSON_OPTION,
) -> None:
    """Import a JIGSAWS/COMPASS gesture transcription as frame labels.

    The transcription's frame ranges are inclusive.

    Example: midas labels import-transcription Suturing_S02_T01.txt sessions/Suturing_S02_T1_20260101T120000Z
    """
    options = ImportOptions(taxonomy_name, gaps, overlap, name, force)
    _report(import_transcription(file, session, options, index_base), as_json)


def _report(result: ImportResult, as_json: bool) -> None:
    if as_json:
        print_json(result.to_json())
        return
    r, meta = result.report, result.meta
    out.print(f"wrote {result.path}: {sum(r.frame_counts.values())} frames from {r.segments} segment(s), "
              f"taxonomy {meta['taxonomy']}, {meta['fps']:g} fps", markup=False)
    out.print("frames per class: " + ", ".join(f"{k} {v}" for k, v in r.frame_counts.items()), markup=False)
    gap_action = "left unlabelled" if r.gap_mode == "unlabelled" else "filled with the idle class"
    lines = ([f"overlap: {o['a']} and {o['b']} ({'/'.join(o['labels'])}) share frames {o['first']}..{o['last']} "
              f"({o['frames']}); the {r.overlap_rule}-starting segment keeps them" for o in r.overlaps]
             + [f"gap: frames {g['first']}..{g['last']} ({g['frames']}, {g['where']}): {gap_action}" for g in r.gaps]
             + [f"clipped: {c['segment']} ({c['label']}) lost {c['frames_cut']} frame(s) {_SIDES[c['side']]}: "
                f"the video has frames {c['video_frames'][0]}..{c['video_frames'][1]}" for c in r.clipped]
             + [f"dropped: {d['segment']} ({d['label']}, frames {d['first']}..{d['last']}): {d['reason']}"
                for d in r.dropped]
             + [f"skipped: {s['segment']}: {s['reason']}" for s in r.skipped])
    for line in lines[:MAX_LISTED]:
        out.print(line, markup=False)
    if len(lines) > MAX_LISTED:
        out.print(f"... and {len(lines) - MAX_LISTED} more (see --json)")


@app.command()
def export(
    session: Path = SESSION_ARG,
    fmt: str = typer.Option(..., "--format", help=f"One of {', '.join(EXPORT_FORMATS)}: VIA 3 project JSON, "
                            "VIA 3 CSV export, or a plain CSV of segments."),
    name: str = NAME_OPTION,
    out_file: Optional[Path] = typer.Option(None, "--out", help="Write here instead of stdout."),
) -> None:
    """Export a label set as segments, for VIA (re-annotation) or other tools.

    `midas labels import-via` reads the VIA formats back to the same frame labels.

    Example: midas labels export sessions/suturing_S1_T3_20260101T120000Z --format via --out trial3.json
    """
    text = export_labels(session, fmt, name)
    if out_file is None:
        sys.stdout.write(text)
        return
    write_text(out_target(out_file, inputs=label_set_files(session, name)), text)
    err.print(f"wrote {out_file}", markup=False)


@app.command()
def stats(
    paths: list[Path] = typer.Argument(..., help="Session folders and/or transcription files or folders of them."),
    name: str = NAME_OPTION,
    taxonomy_name: Optional[str] = typer.Option(None, "--taxonomy", help="Taxonomy for names and class order "
                                                "(default: the one the sessions' labels name)."),
    frame_rate: Optional[float] = typer.Option(None, "--frame-rate", callback=positive, help="Frame rate of "
                                               "transcription files, Hz (default 30)."),
    old_fps: Optional[float] = renamed_option("--fps", "--frame-rate"),
    exclude: list[str] = typer.Option([], "--exclude", help="Leave out this label (repeatable), e.g. Idle."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Also write the transition matrix as a PNG heatmap."),
    as_json: bool = JSON_OPTION,
) -> None:
    """Gesture segment counts, durations and transitions (the dataset table).

    Per-gesture segment counts and mean ± std duration (the paper's dataset table), totals, and the
    gesture transition matrix, over sessions and/or transcription files.

    Example: midas labels stats ../shared/data/compass-suturing-gestures --taxonomy jigsaws-suturing
    """
    fps = take_renamed(frame_rate, old_fps, "--fps", "--frame-rate", error_line) or JIGSAWS_FPS
    recordings, recorded_taxonomy = load_recordings(paths, name, fps)
    taxonomy = load_taxonomy(taxonomy_name) if taxonomy_name else _recorded_taxonomy(recorded_taxonomy)
    result = gesture_stats(recordings, taxonomy, exclude)
    if plot is not None:
        transition_heatmap(result, plot)
        err.print(f"wrote {plot}", markup=False)
    if as_json:
        print_json(result.to_json())
        return
    _print_stats(result)


def _recorded_taxonomy(name: Optional[str]) -> Optional[Taxonomy]:
    """The shipped taxonomy the label sets name; None (a warning: classes in their order of appearance)
    when it is not one midas ships (a label set made with a taxonomy file of its own: only the name is
    recorded, and a name from the data is never read as a path)."""
    if name is None:
        return None
    try:
        return shipped_taxonomy(name)
    except ConfigError:
        error_line(f"midas: warning: the label sets name taxonomy {name!r}, which midas does not ship: gestures in "
                   "the order they appear (give --taxonomy FILE for its order and names)")
        return None


def _print_stats(result: GestureStats) -> None:
    data: dict[str, Any] = result.to_json()
    table = Table("ID", "Gesture", "Samples", "Avg. Dur. (s)", header_style="bold")
    for row in data["gestures"]:
        std = "—" if row["std_s"] is None else f"{row['std_s']:.2f}"
        table.add_row(row["id"], row["name"], str(row["samples"]), f"{row['mean_s']:.2f} ± {std}")
    table.add_row("", f"Total: {data['classes']}", str(data["samples"]), f"{data['total_min']:.0f} (min)")
    table.add_row("", f"{data['recordings']} recording(s)", "", f"~{data['min_per_recording']:.1f} min/recording")
    out.print(table)
    matrix = Table("from \\ to", *result.classes, title="transitions (consecutive segments)", header_style="bold")
    for label, row in zip(result.classes, result.transitions):
        matrix.add_row(label, *[str(v) if v else "·" for v in row])
    out.print(matrix)
