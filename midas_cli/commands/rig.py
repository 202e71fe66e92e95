"""`midas rig check`: pre-flight check of a rig's devices (open, read a few seconds, close; records nothing)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from midas_cli.commands.common import out, positive, print_json
from midas_cli.commands.options import JSON_OPTION
from midas_cli.errors import ConfigError, DeviceError

app = typer.Typer(no_args_is_help=True, help="Check a rig's devices before recording.\n\n"
                  "Example: midas rig check sessions_template/rigs/simulated.toml")


@app.command("check")
def check(
    rig: Optional[Path] = typer.Argument(None, help="Rig file (TOML; templates in sessions_template/rigs/; default: "
                                         "$MIDAS_RIG or [record] rig in the config)."),
    simulate: bool = typer.Option(False, "--simulate", help="Check the built-in simulated rig."),
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
    from midas_cli.devices.rigconfig import load_rig
    from midas_cli.record.rigcheck import check_rig
    from midas_cli.rig import simulated_rig

    from midas_cli.config import RIG_ENV, config_path, default_rig

    if simulate and rig is not None:
        raise ConfigError("give a rig file or --simulate (one of them)")
    if not simulate and rig is None:
        rig = default_rig()
        if rig is None:
            raise ConfigError(f"give a rig file or --simulate (or set {RIG_ENV} or [record] rig in {config_path()})")
    config = simulated_rig() if simulate else load_rig(rig)
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
