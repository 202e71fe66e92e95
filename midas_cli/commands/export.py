"""`midas export`: sessions out to MCAP, Parquet, XDF and LeRobot datasets."""

from __future__ import annotations

from pathlib import Path

import typer

from midas_cli.commands.common import err, out, print_json
from midas_cli.commands.options import JSON_OPTION, SESSIONS_ARG
from midas_cli.interop.export import export_session, format_help, parse_formats  # light: writers load lazily


def export(sessions: list[Path] = SESSIONS_ARG,
           formats: list[str] = typer.Option(..., "--format", help=format_help()),
           out_dir: Path = typer.Option(..., "--out", help="Folder that receives the files (created if missing)."),
           with_video: bool = typer.Option(False, "--with-video", help="MCAP: also the RGB-D frames as JPEG "
                                           "images and the console recording as H.264 video (every frame "
                                           "decoded and re-encoded: slow; the video needs ffmpeg)."),
           as_json: bool = JSON_OPTION) -> None:
    """Export sessions as MCAP (Foxglove), Parquet, XDF (LSL) and/or LeRobot datasets.

    Per session: <out>/<id>.mcap (for Foxglove: a topic per stream, EmHT poses, markers as logs, labels,
    the manifest as metadata; --with-video: the RGB-D frames as images, the console video as H.264),
    <out>/<id>/<stream>.parquet (+ labels_<set>.parquet, aligned.parquet), <out>/<id>.xdf (a stream per
    stream, units in the headers, clock offsets 0: the host clock is the session's only clock),
    <out>/<id>.lerobot/ (a LeRobot v3.0 dataset of one episode on the aligned frame clock; needs
    `midas align` first).
    Streams are read and written a piece at a time.

    Example: midas export sessions/suturing_S1_T1_20240703T104640Z --format mcap,parquet,xdf --out exported
    """
    wanted = parse_formats(formats)
    results = []
    for path in sessions:
        result = export_session(path, wanted, out_dir, progress=lambda what: err.print(
            f"exporting {what}", markup=False, highlight=False), with_video=with_video)
        results.append(result)
    if as_json:
        print_json(results)
        return
    for result in results:
        for name in wanted:
            written = result[name]
            out.print(written.get("file") or written.get("folder"), markup=False, highlight=False, soft_wrap=True)
