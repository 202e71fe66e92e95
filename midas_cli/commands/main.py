"""The `midas` entry point: command registration and the error -> exit code mapping."""

from __future__ import annotations

import logging
import sys
import traceback

import typer

from midas_cli import __version__
from midas_cli.commands import doctor as doctor_cmd
from midas_cli.commands import labels as labels_cmd
from midas_cli.commands import record as record_cmd
from midas_cli.commands import session as session_cmd
from midas_cli.commands.common import STDERR_LOG, error_line
from midas_cli.errors import MidasError

app = typer.Typer(
    help="midas: record and analyse multimodal data in robot-assisted surgery (MiDAS).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)
app.command("record")(record_cmd.record)
app.add_typer(session_cmd.app, name="session")
app.add_typer(labels_cmd.app, name="labels")
app.command("doctor")(doctor_cmd.doctor)

_state = {"debug": False}


def _version(value: bool) -> None:
    if value:
        sys.stdout.write(f"midas {__version__}\n")
        raise typer.Exit()


@app.callback()
def main(
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks and debug logging."),
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
) -> None:
    """Every command reads and writes self-describing session folders; results go to stdout,
    progress and errors to stderr. Exit codes: 0 ok, 1 internal, 2 usage, 3 device, 4 session/data."""
    _state["debug"] = debug
    STDERR_LOG.setLevel(logging.DEBUG if debug else logging.WARNING)
    STDERR_LOG.setFormatter(logging.Formatter("midas: %(levelname)s %(name)s: %(message)s"))
    logging.getLogger().addHandler(STDERR_LOG)


def run() -> None:
    try:
        app(prog_name="midas")
    except MidasError as exc:
        if _state["debug"]:
            traceback.print_exc()
        error_line(f"midas: error: {exc}")
        sys.exit(exc.exit_code)
    except Exception as exc:  # the one place that turns surprises into exit code 1
        if _state["debug"]:
            traceback.print_exc()
        error_line(f"midas: internal error: {type(exc).__name__}: {exc} (run with --debug for a traceback)")
        sys.exit(1)
