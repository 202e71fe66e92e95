"""`midas emulate ...`: byte-faithful device emulators on pseudo-terminals (for tests and dry runs)."""

from __future__ import annotations

import signal
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer

from midas_cli.commands.common import err, finite, non_negative, positive, print_json, probability
from midas_cli.commands.options import JSON_OPTION
from midas_cli.errors import ConfigError

if TYPE_CHECKING:
    from midas_cli.devices.fps.emulator import FpsEmulator
    from midas_cli.devices.pty_emulator import PtyEmulator

app = typer.Typer(help="Serve emulated serial devices on pseudo-terminals.", no_args_is_help=True)

# The options every pty emulator shares (one fault vocabulary: midas_cli.devices.pty_emulator.Faults)
SEED = typer.Option(0, "--seed", help="Seed of the simulated surgeon's motion and of the faults.")
CORRUPT = typer.Option(0.0, "--corrupt", callback=probability, help="Probability per byte of line noise replacing it.")
DROP = typer.Option(0.0, "--drop", callback=probability, help="Probability per byte of losing it.")
STALL_AT = typer.Option(-1.0, "--stall-at", callback=finite, help="Seconds after start: send nothing (see --stall-for).")
STALL_FOR = typer.Option(0.0, "--stall-for", callback=non_negative, help="Length of the stall in seconds.")
UNPLUG_AT = typer.Option(-1.0, "--unplug-at", callback=finite, help="Seconds after start: pull the cable (needs --link).")
UNPLUG_FOR = typer.Option(0.0, "--unplug-for", callback=non_negative, help="Seconds until the pty is reopened at --link.")
LINK = typer.Option(None, "--link", help="Symlink that always points at the current pty.")
SUMMARY = typer.Option(None, "--summary", help="Write what was sent as JSON here at exit.")
DURATION = typer.Option(None, "--duration", callback=positive, help="Stop after this many seconds.")


@app.command()
def trakstar(
    sensors: int = typer.Option(4, "--sensors", help="Sensors attached to the tracker (1..4; the host may use fewer)."),
    baud: int = typer.Option(115200, "--baud", help="Line speed the output is paced to (8N1)."),
    seed: int = SEED, corrupt: float = CORRUPT, drop: float = DROP, stall_at: float = STALL_AT,
    stall_for: float = STALL_FOR, unplug_at: float = UNPLUG_AT, unplug_for: float = UNPLUG_FOR,
    link: Optional[Path] = LINK, summary: Optional[Path] = SUMMARY, duration: Optional[float] = DURATION,
    as_json: bool = JSON_OPTION,
) -> None:
    """Serve the trakSTAR's Flock-of-Birds RS-232 protocol on a pty.

    Serve the trakSTAR's Flock-of-Birds RS-232 protocol on a pty, paced to the baud rate, with the
    simulated surgeon's motion and optional faults. Prints the port path (the --link if given) as
    the first stdout line; stops on Ctrl-C, SIGTERM or --duration and reports what it sent.

    Example: midas emulate trakstar --link /tmp/trakstar --summary /tmp/trakstar.json --corrupt 0.01
    """
    from midas_cli.devices.pty_emulator import Faults
    from midas_cli.devices.trakstar.emulator import EmulatorConfig, TrakstarEmulator

    faults = Faults(corrupt, drop, stall_at, stall_for, unplug_at, unplug_for)
    emulator = TrakstarEmulator(EmulatorConfig(sensors, baud, seed, faults, str(link) if link else None))
    result = _serve(emulator, duration, summary)
    err.print(f"trakstar emulator: {result['stream_groups_sent']} cycles streamed, records per sensor "
              f"{result['records_per_sensor']}, {result['bytes_corrupted']} bytes corrupted, "
              f"{result['bytes_dropped']} dropped, {len(result['unplugs'])} unplug(s)")
    if as_json:
        print_json({k: v for k, v in result.items() if k not in ("stream_counters", "stream_t_model_s")})


def _serve(emulator: PtyEmulator, duration: Optional[float], summary: Optional[Path], controls=None) -> dict:
    """Print the port path, serve until a signal or ``duration``, stop, write the summary; return it."""
    stopped = _stop_on_signals()
    emulator.start()
    sys.stdout.write(emulator.path + "\n")
    sys.stdout.flush()
    if controls is not None:
        threading.Thread(target=controls, args=(emulator,), daemon=True).start()
    try:
        emulator.serve_for(duration, lambda: stopped["signal"] is not None)
    finally:
        result = emulator.stop()
        if summary is not None:
            emulator.write_summary(summary)
    return result


def _stop_on_signals() -> dict:
    """SIGINT/SIGTERM end the emulation cleanly (the summary is still written)."""
    stopped: dict = {"signal": None}

    def handle(signum: int, _frame) -> None:
        stopped["signal"] = signum

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handle)
    return stopped


@app.command()
def fps(
    channels: int = typer.Option(9, "--channels", help="FSR channels on the board (1..9)."),
    rate: int = typer.Option(250, "--rate", callback=positive, help="Sample rate at boot in Hz (the host sets its own with RATE)."),
    baud: int = typer.Option(500000, "--baud", help="The firmware's line speed (limits the rate it accepts)."),
    pedals: str = typer.Option("model", "--pedals", help="model: the surgeon presses pedals; idle: feet at rest."),
    seed: int = SEED, corrupt: float = CORRUPT, drop: float = DROP, stall_at: float = STALL_AT,
    stall_for: float = STALL_FOR, unplug_at: float = UNPLUG_AT, unplug_for: float = UNPLUG_FOR,
    link: Optional[Path] = LINK, summary: Optional[Path] = SUMMARY, duration: Optional[float] = DURATION,
    as_json: bool = JSON_OPTION,
) -> None:
    """Serve the FPS pedal board's MIDAS-FPS line protocol on a pty.

    Serve the FPS pedal board's MIDAS-FPS line protocol (firmware/fps/PROTOCOL.md) on a pty, paced
    by its sample clock, with the simulated surgeon's feet and optional faults. Prints the port
    path (the --link if given) as the first stdout line. Lines on stdin control it: `press N`,
    `release N`, `auto N`, `unplug`, `replug`. Stops on Ctrl-C, SIGTERM or --duration and reports
    what it sent. An unplug is a reboot of the board.

    Example: midas emulate fps --link /tmp/fps --summary /tmp/fps.json --corrupt 0.01
    """
    from midas_cli.devices.fps.emulator import FpsEmulator, FpsEmulatorConfig
    from midas_cli.devices.pty_emulator import Faults

    faults = Faults(corrupt, drop, stall_at, stall_for, unplug_at, unplug_for)
    config = FpsEmulatorConfig(channels, rate, baud, seed, pedals, faults=faults, link=link,
                               keep_samples=summary is not None)
    result = {k: v for k, v in _serve(FpsEmulator(config), duration, summary, _stdin_controls).items()
              if k != "samples"}
    err.print(f"fps emulator: {result['sent']} samples sent ({result['intact']} intact), "
              f"{result['bytes_corrupted']} bytes corrupted, {result['bytes_dropped']} dropped, "
              f"{len(result['boots'])} boot(s)")
    if as_json:
        print_json(result)


def _stdin_controls(emulator: FpsEmulator) -> None:
    """Apply control lines from stdin until EOF; a bad line is reported and skipped."""
    for line in sys.stdin:
        if not line.strip():
            continue
        try:
            emulator.control(line)
        except ConfigError as exc:
            err.print(f"midas: error: {exc}", markup=False, highlight=False)


@app.command()
def raven(
    to: str = typer.Option("127.0.0.1:36000", "--to", help="HOST:PORT the console's UDP packets go to."),
    source: str = typer.Option("", "--from", help="HOST or HOST:PORT to send from (e.g. 127.0.0.2 to play a "
                                                  "stranger on loopback); default: what the route picks."),
    rate: float = typer.Option(1000.0, "--rate", callback=positive, help="Packets per second."),
    seed: int = typer.Option(0, "--seed", help="Seed of the simulated surgeon's hands and clutch pedal."),
    corrupt_every: int = typer.Option(0, "--corrupt-every", help="After every N packets send a wrong-size one."),
    duration: Optional[float] = typer.Option(None, "--duration", callback=positive, help="Stop after this many seconds."),
    as_json: bool = JSON_OPTION,
) -> None:
    """Send Raven-II surgeon-console telemetry as UDP packets.

    Send Raven-II surgeon-console telemetry (124-byte u_struct UDP packets) following the simulated
    surgeon: position increments, orientations, grasp and the clutch as surgeon_mode. Stops on
    Ctrl-C, SIGTERM or --duration and reports how many packets it sent.

    Example: midas emulate raven --to 127.0.0.1:36000 --rate 1000 --duration 10
    """
    from midas_cli.devices.raven.device import parse_address
    from midas_cli.devices.raven.emulator import RavenEmulator, RavenEmulatorConfig

    host, port = parse_address(to, "--to")
    emulator = RavenEmulator(RavenEmulatorConfig(host, port, rate, seed, corrupt_every, source),
                             keep_sent=False).start()
    stopped = _stop_on_signals()
    deadline = None if duration is None else time.monotonic() + duration
    try:
        while stopped["signal"] is None and (deadline is None or time.monotonic() < deadline):
            time.sleep(0.05)
    finally:
        result = emulator.stop()
    err.print(f"raven emulator: {result['packets_sent']} packets sent to {host}:{port}"
              f"{' from ' + source if source else ''}, "
              f"{result['wrong_size_sent']} wrong-size")
    if as_json:
        print_json(result)
