"""`midas rig check|show`: a rig's devices before recording: open and read each a few seconds (records
nothing), or list what `midas record` would open."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer
from rich.table import Table

from midas_cli.commands.common import out, positive, print_json
from midas_cli.commands.options import JSON_OPTION
from midas_cli.errors import ConfigError, DeviceError

if TYPE_CHECKING:
    from midas_cli.devices.rigconfig import RigConfig

app = typer.Typer(no_args_is_help=True, help="Check or list a rig's devices before recording.\n\n"
                  "Example: midas rig check sessions_template/rigs/simulated.toml")

RIG_ARG = typer.Argument(None, help="Rig file (TOML; templates in sessions_template/rigs/; default: $MIDAS_RIG or "
                         "[record] rig in the config).")
SIMULATE_OPTION = typer.Option(False, "--simulate", help="The built-in simulated rig.")


@app.command("check")
def check(
    rig: Optional[Path] = RIG_ARG,
    simulate: bool = SIMULATE_OPTION,
    seconds: float = typer.Option(3.0, "--seconds", callback=positive, help="Seconds to read from each device."),
    as_json: bool = JSON_OPTION,
) -> None:
    """Open every device of a rig, read a few seconds, report health and rates.

    Each device is opened as `midas record` opens it (all at once), read for --seconds and closed;
    the table shows per device its state (ok / failed / skipped), streams, measured vs nominal rate
    and the error; below it, per serial device, the USB adapter behind its port, its latency timer
    (set to 1 ms where permitted, else how to) and the port's low-latency flag. Nothing is recorded
    and no file is written (an adapter's latency timer aside). obs:// and raven:// devices work only
    inside a session folder and are skipped (`midas doctor` checks OBS). Exit 3 when any device
    failed.

    Example: midas rig check sessions_template/rigs/simulated.toml --seconds 3
    """
    from midas_cli.record.rigcheck import check_rig

    config = _the_rig(rig, simulate)
    results = check_rig(config, seconds)
    failed = [r.device for r in results if r.state == "failed"]
    if as_json:
        print_json({"rig": config.name, "source": config.source, "seconds": seconds, "ok": not failed,
                    "devices": [r.as_dict() for r in results]})
    else:
        table = Table(title=f"rig {config.name} ({config.source}): {seconds:g} s per device")
        for column in ("device", "state", "stream", "samples", "measured / nominal Hz", "error"):
            table.add_column(column)
        for r in results:
            entries = r.as_dict()["streams"] or {"-": None}
            for k, (name, s) in enumerate(entries.items()):
                rate = "-" if s is None else (f"{s['measured_hz']:.1f} / {s['nominal_hz']:g}" if s["nominal_hz"]
                                              else f"{s['measured_hz']:.1f} / events")
                table.add_row(r.device if k == 0 else "", r.state if k == 0 else "", name,
                              "-" if s is None else str(s["samples"]), rate, (r.error or "") if k == 0 else "")
        out.print(table)
        for r in results:
            if r.serial_line():
                out.print(f"{r.device} serial port: {r.serial_line()}", markup=False, soft_wrap=True)
    if failed:
        raise DeviceError(f"rig check: {len(failed)} device(s) failed: {', '.join(failed)}")


@app.command("show")
def show(rig: Optional[Path] = RIG_ARG, simulate: bool = SIMULATE_OPTION, as_json: bool = JSON_OPTION) -> None:
    """List the devices a rig gives `midas record`: name, kind and URL.

    Opens nothing. URLs are shown as a manifest records them (a password source named, never a
    password). Without a rig file it shows the default rig and where that came from.

    Example: midas rig show sessions_template/rigs/simulated.toml
    """
    config = _the_rig(rig, simulate)
    summary = config.to_manifest()
    if as_json:
        print_json(summary)
        return
    table = Table("device", "kind", "url", title=f"rig {config.name} ({config.source}), platform {config.platform}")
    for name, device in summary["devices"].items():
        table.add_row(name, device["kind"], device["url"])
    out.print(table)


def _the_rig(rig: Optional[Path], simulate: bool) -> RigConfig:
    """The rig a command was given: a rig file, the simulated rig, else the configured default."""
    from midas_cli.config import RIG_ENV, config_path, default_rig
    from midas_cli.devices.rigconfig import load_rig
    from midas_cli.rig import simulated_rig

    if simulate and rig is not None:
        raise ConfigError("give a rig file or --simulate (one of them)")
    if not simulate and rig is None:
        rig = default_rig()
        if rig is None:
            raise ConfigError(f"give a rig file or --simulate (or set {RIG_ENV} or [record] rig in {config_path()})")
    return simulated_rig() if simulate else load_rig(rig)
