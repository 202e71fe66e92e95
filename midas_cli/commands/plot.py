"""`midas plot SESSION`: one quick-look PNG of a session (every stream, rates, gaps, pedals, labels)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from midas_cli.commands.common import out, print_json
from midas_cli.commands.options import JSON_OPTION, SESSION_ARG


def plot(
    session: Path = SESSION_ARG,
    out_path: Optional[Path] = typer.Option(None, "--out", help="PNG to write; default: "
                                            "SESSION/derived/plots/quicklook.png."),
    as_json: bool = JSON_OPTION,
) -> None:
    """Draw a quick-look page of a session: every stream against session time.

    One PNG titled with the session name: each stream's rate per second against its nominal rate,
    EmHT positions per sensor, the pedal board's pressed states, HandKP thumb-middle distance with
    its detection gaps, video frame intervals, any other stream's first columns, and the gesture
    label ribbon (labels/gestures.csv, grey = unlabelled). Sequence gaps the manifest lists (red)
    and device outages (orange: lost until reopened) are shaded. Nothing in the recording changes.
    --json lists the panels drawn and the gaps shaded.

    Example: midas plot sessions/suturing_S1_T1_20240703T104640Z --out quicklook.png
    """
    from midas_cli.analysis.quicklook import quicklook  # matplotlib only for this command

    result = quicklook(session, out_path)
    if as_json:
        print_json(result.as_dict())
        return
    for gap in result.gaps:
        out.print(f"{gap.stream}: {gap.kind.replace('_', ' ')} {gap.start_s:.2f}-{gap.end_s:.2f} s"
                  + (f" ({gap.missing} samples missing)" if gap.missing else ""), markup=False)
    out.print(f"{len(result.panels)} panels, {len(result.gaps)} gap(s) shaded", markup=False)
    out.print(str(result.out), markup=False, soft_wrap=True)
