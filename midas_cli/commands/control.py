"""`midas mark` and `midas ctl`: talk to a running `midas record` over its control socket."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Optional

import typer

from midas_cli.commands.common import print_json

CONTROL_HELP = "The recording's control socket (default: the one running recording of this user)."
app = typer.Typer(no_args_is_help=True, help="Remote control of a running recording (start, stop, status, mark).\n\n"
                  "Local only: a Unix socket (mode 0600) that `midas record` opens; one JSON line each way.\n\n"
                  "Example: midas ctl status")


def mark(text: str = typer.Argument(..., help="The marker's text (one line)."),
         control: Optional[Path] = typer.Option(None, "--control", help=CONTROL_HELP)) -> None:
    """Add a marker to the running recording's events stream.

    The row (seq, host time, text, source "mark") is on disk when this returns; its JSON is printed.
    Without --control, the one recording this user runs is found; with none running, exit 4.

    Example: midas mark "needle passed"
    """
    print_json(_ask(control, {"cmd": "mark", "text": text, "source": "mark"}))


@app.callback()
def _options(ctx: typer.Context,
             control: Optional[Path] = typer.Option(None, "--control", help=CONTROL_HELP)) -> None:
    ctx.obj = control


@app.command("status")
def status(ctx: typer.Context) -> None:
    """Print the recording's state as JSON: session, state, device health, duration.

    Example: midas ctl status | jq -r .state
    """
    print_json(_ask(ctx.obj, {"cmd": "status"}))


@app.command("mark")
def ctl_mark(ctx: typer.Context, text: str = typer.Argument(..., help="The marker's text (one line).")) -> None:
    """Add a marker (source "ctl") to the events stream; print its row as JSON.

    Example: midas ctl --control /run/user/1000/midas/record-4242.sock mark "suture 2"
    """
    print_json(_ask(ctx.obj, {"cmd": "mark", "text": text, "source": "ctl"}))


@app.command("start")
def start(ctx: typer.Context) -> None:
    """Start an armed recording (`midas record --armed`); --duration counts from now.

    Example: midas record --rig rig.toml --armed ... & midas ctl start
    """
    print_json(_ask(ctx.obj, {"cmd": "start"}))


@app.command("stop")
def stop(ctx: typer.Context,
         timeout: float = typer.Option(60.0, "--timeout", help="Seconds to wait for the finalised manifest.")) -> None:
    """Stop the recording as Ctrl-C does; print its status once the manifest is final.

    Example: midas ctl stop
    """
    from midas_cli.errors import SessionError
    from midas_cli.processes import process_alive
    from midas_cli.session.manifest import load_manifest

    path = _socket(ctx.obj)
    reply = _ask(path, {"cmd": "stop"})
    deadline = time.monotonic() + timeout
    # the recorder removes its socket once the session is finalised (a killed one leaves it: its pid is gone)
    while path.exists() and process_alive(reply["pid"]):
        if time.monotonic() > deadline:
            raise SessionError(f"the recorder at {path} did not finish within {timeout:g} s "
                               f"(session {reply.get('session_path')})")
        time.sleep(0.1)
    manifest = load_manifest(Path(reply["session_path"]))
    print_json({"state": "stopped", "session_path": reply["session_path"], "status": manifest["status"],
                "stop_reason": manifest["stop_reason"]})


def _socket(control: Optional[Path]) -> Path:
    """The socket given, or the default one of this user's running recording."""
    from midas_cli.errors import ConfigError, SessionError
    from midas_cli.record.control import default_control_dir, running_recordings

    if control is not None:
        return control
    folder = default_control_dir()
    found = running_recordings(folder)
    if not found:
        raise SessionError(f"no recording is running (no control socket in {folder}); start `midas record`, "
                           f"or give --control PATH")
    if len(found) > 1:
        raise ConfigError(f"{len(found)} recordings are running ({', '.join(p.name for p in found)} in {folder}); "
                          f"give --control PATH")
    return found[0]


def _ask(control: Optional[Path], request: dict[str, Any]) -> dict[str, Any]:
    """The recorder's reply to ``request``; its refusal raised as the error class it came from."""
    from midas_cli.errors import ConfigError, DeviceError, MidasError, SessionError
    from midas_cli.record.control import send_request

    reply = send_request(_socket(control), request)
    if not reply.pop("ok", False):
        kind = {2: ConfigError, 3: DeviceError, 4: SessionError}.get(reply.get("exit_code"), MidasError)
        raise kind(f"the recorder refused: {reply.get('error', 'no reason given')}")
    return reply
