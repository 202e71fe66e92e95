"""`midas calibrate ...`: calibrations that produce settings for a rig (pedal thresholds: `fps`)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer
from rich.live import Live
from rich.table import Table
from rich.text import Text

from midas_cli.commands import calibrate_analysis
from midas_cli.commands.common import err, out, positive, print_json
from midas_cli.commands.options import JSON_OPTION
from midas_cli.errors import ConfigError

if TYPE_CHECKING:
    from midas_cli.devices.fps.calibration import FpsCalibration, LiveCalibration
    from midas_cli.devices.fps.rigfile import FpsTarget
    import numpy as np

app = typer.Typer(help="Calibrate devices and write the results into a rig file.", no_args_is_help=True)

BAR_WIDTH = 30
PLAIN_EVERY_S = 1.0


@app.command()
def fps(
    rig: Path = typer.Option(..., "--rig", help="Rig file: the pedal mapping is read from it and the thresholds "
                             "written into its device URL (created if missing).", dir_okay=False),
    device: str = typer.Option("fps", "--device", help="The pedal board's device name ([devices.NAME])."),
    url: Optional[str] = typer.Option(None, "--url", help="Use this fps:// URL instead of the rig file's."),
    session: Optional[Path] = typer.Option(None, "--session", help="Compute the thresholds from this recorded "
                                           "session instead of live prompts (non-interactive).", file_okay=False),
    rest_s: float = typer.Option(3.0, "--rest-s", callback=positive, help="Seconds measured with the feet off all pedals."),
    press_s: float = typer.Option(3.0, "--press-s", callback=positive, help="Seconds measured while each pedal is held."),
    dry_run: bool = typer.Option(False, "--dry-run", help="Show the thresholds; do not change the rig file."),
    as_json: bool = JSON_OPTION,
) -> None:
    """Calibrate the FPS pedal board's per-pedal press/release thresholds.

    Per-pedal press/release thresholds (with hysteresis) for the FPS pedal board. Live (a terminal,
    also over SSH): measure every channel at rest, then press and hold each mapped pedal in turn
    while live bars show the voltages. With --session: from a recording, no prompts. Channels that
    do not separate keep their thresholds and are flagged. The result goes into the rig file's
    fps:// URL.

    Example: midas calibrate fps --rig sessions_template/rigs/davinci-xi.toml --url fps:///dev/ttyACM0
    """
    from midas_cli.devices.fps.calibration import calibrate_from_session
    from midas_cli.devices.fps.rigfile import load_target, write_target

    target = load_target(rig, device, url)
    if session is not None:
        result = calibrate_from_session(session, device, target.pedals, target.thresholds)
    else:
        result = _interactive(target, rest_s, press_s)
    written = None if dry_run else write_target(target, result.thresholds)
    _render(result, as_json)
    for channel in result.channels:
        if not channel.separated:
            err.print(f"warning: channel {channel.channel} ({channel.pedal}) does not separate: {channel.note}; "
                      "it keeps its previous thresholds", markup=False)
    err.print(f"wrote {rig}: url = {written}" if written else "dry run: rig file not changed", markup=False)


def _interactive(target: FpsTarget, rest_s: float, press_s: float) -> FpsCalibration:
    """The prompted procedure: rest, then each mapped pedal pressed and held."""
    from midas_cli.devices.fps.calibration import calibrate_live, LiveCalibration

    live = LiveCalibration(target.url, target.device)
    info = live.open()
    err.print(f"connected: {info['port']}, MIDAS-FPS firmware {info['firmware']}, {live.channels} channels",
              markup=False)
    try:
        _ask("Feet off all pedals. Press Enter to measure the rest level")
        rest = _measure(live, target, rest_s, "rest", None)
        presses = {}
        for channel, pedal in sorted(target.pedals.items()):
            _ask(f"Channel {channel} = {pedal}: press Enter, then press and hold the pedal until the bar is full")
            presses[channel] = _measure(live, target, press_s, f"hold {pedal}", channel)
            err.print(f"Release {pedal}.", markup=False)
    finally:
        live.close()
    return calibrate_live(rest, presses, target.pedals, target.thresholds)


def _ask(prompt: str) -> None:
    err.print(f"{prompt} [Enter] ", end="", markup=False)
    if not sys.stdin.readline():
        raise ConfigError("live calibration needs an operator at a terminal (stdin closed); use --session")


def _measure(live: LiveCalibration, target: FpsTarget, seconds: float, what: str, channel: int | None) -> np.ndarray:
    """Measure with live bars on a terminal, or a plain line per second otherwise."""
    if not err.is_terminal:
        last = [0.0]

        def plain(elapsed: float, volts: np.ndarray) -> None:
            if elapsed - last[0] >= PLAIN_EVERY_S:
                last[0] = elapsed
                err.print(f"{what} {elapsed:4.1f}/{seconds:g} s: " + " ".join(f"{v:.2f}" for v in volts), markup=False)

        return live.measure(seconds, plain)
    with Live(console=err, refresh_per_second=10, transient=True) as screen:
        return live.measure(seconds, lambda t, v: screen.update(_bars(target, v, t / seconds, what, channel)))


def _bars(target: FpsTarget, volts: np.ndarray, done: float, what: str, active: int | None) -> Table:
    """One bar per channel (0..Vcc), the channel being pressed highlighted, and the elapsed fraction."""
    from midas_cli.devices.pedals import VCC

    table = Table.grid(padding=(0, 1))
    table.add_row(Text(f"{what}: "), Text("█" * int(done * BAR_WIDTH) + "·" * (BAR_WIDTH - int(done * BAR_WIDTH))))
    for c, value in enumerate(volts, start=1):
        filled = int(round(min(value, VCC) / VCC * BAR_WIDTH))
        style = "bold magenta" if c == active else "magenta"
        name = target.pedals.get(c, "")
        table.add_row(Text(f"ch{c} {name[:22]:22}"), Text("█" * filled + "·" * (BAR_WIDTH - filled), style),
                      Text(f"{value:4.2f} V"))
    return table


def _render(result: FpsCalibration, as_json: bool) -> None:
    if as_json:
        print_json(result.to_json())
        return
    table = Table("channel", "pedal", "rest V", "pressed V", "press_v", "release_v", "status",
                  title=f"FPS thresholds ({result.source})", header_style="bold")
    for c in result.channels:
        level = "—" if c.level_v is None else f"{c.level_v:.2f}"
        status = ("ok" if c.separated else "FLAGGED") + (f": {c.note}" if c.note else "")
        table.add_row(str(c.channel), c.pedal, f"{c.rest_v:.2f}", level, f"{c.press_v:.3f}", f"{c.release_v:.3f}",
                      status)
    out.print(table)

app.command("emht")(calibrate_analysis.emht)
app.command("handkp")(calibrate_analysis.handkp)
app.command("fps-optimize")(calibrate_analysis.fps_optimize)
