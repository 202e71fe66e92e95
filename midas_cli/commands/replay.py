"""`midas replay`: play a recorded session back as live LSL streams."""

from __future__ import annotations

import signal
from pathlib import Path

import typer

from midas_cli.commands.common import error_line, non_negative, positive
from midas_cli.commands.options import SESSION_ARG
from midas_cli.errors import ConfigError

TARGETS = ("lsl",)
STOP_SIGNALS = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}


def replay(session: Path = SESSION_ARG,
           to: str = typer.Option("lsl", "--to", help="Where to publish: lsl (one LSL outlet per stream)."),
           speed: float = typer.Option(1.0, "--speed", callback=positive, help="Play this many times faster "
                                       "than recorded (timestamps keep the recorded spacing)."),
           loop: bool = typer.Option(False, "--loop", help="Start again after the last sample, until Ctrl-C."),
           streams: list[str] = typer.Option([], "--streams", help="Only these streams (comma-separated or "
                                             "repeated; default: all)."),
           delay: float = typer.Option(1.0, "--delay", callback=non_negative, help="Seconds between announcing "
                                       "the outlets and the first sample, for consumers to connect.")) -> None:
    """Play a session's streams back as live LSL outlets with their recorded timing.

    One outlet per stream: name = the stream, type = its device's kind, source_id =
    midas:<session>:<stream>, a double64 channel per data column (labels and units in the stream's
    description), the manifest's nominal rate (0 for event streams). Each sample is sent at its
    recorded time after the first sample's (divided by --speed), stamped with that time on the
    local LSL clock. Ctrl-C stops (exit 0).

    Example: midas replay sessions/suturing_S1_T1_20240703T104640Z --to lsl --streams emht,fps --loop
    """
    if to.strip().lower() not in TARGETS:
        raise ConfigError(f"--to {to}: expected one of {', '.join(TARGETS)}")
    from midas_cli.commands.progress import progress_display
    from midas_cli.devices.lsl.outlet import exposure_note, lsl_config_file
    from midas_cli.interop.lsl_replay import describe, plan_replay, replay as play

    names = [n.strip() for value in streams for n in value.split(",") if n.strip()]
    plan = plan_replay(session, names, speed, loop, delay)
    error_line(f"midas: {exposure_note(lsl_config_file())}")
    for entry in describe(plan):
        rate = f"{entry['nominal_srate']:g} Hz" if entry["nominal_srate"] else "irregular"
        error_line(f"midas: publishing LSL stream {entry['name']} (type {entry['type']}, {entry['channels']} "
                   f"channel{'s' if entry['channels'] != 1 else ''}, {rate}, source_id {entry['source_id']})")
    stopped_by: list[str] = []
    previous = {sig: signal.signal(sig, lambda signum, _frame: stopped_by.append(STOP_SIGNALS[signum]))
                for sig in STOP_SIGNALS}
    try:
        with progress_display() as progress:
            task = progress.add_task(f"replaying {plan.name}", total=None if loop else plan.samples_per_pass)
            result = play(plan, lambda: bool(stopped_by), lambda now: progress.update(
                task, completed=now.total, passes=f"pass {now.passes}" if loop else ""))
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    passes = f" in {result.passes} pass{'es' if result.passes != 1 else ''}" if loop else ""
    if result.stopped:
        error_line(f"midas: replay stopped by {stopped_by[0]} after {result.total} samples{passes}")
    else:
        error_line(f"midas: replayed {result.total} samples of {len(plan.streams)} streams{passes}")
