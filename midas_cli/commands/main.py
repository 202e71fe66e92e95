"""The `midas` entry point: command registration and the error -> exit code mapping.

Commands are registered from the one command table (``root.REGISTRY``) and only the module of the command
being run is imported (``midas record`` never loads torch or OpenCV). ``midas --version`` and ``midas --help`` never
get here: ``root.answer_without_typer`` answers them from a static table, without importing typer.
"""

from __future__ import annotations

import importlib
import logging
import sys
import traceback

import typer

from midas_cli import __version__
from midas_cli.commands.common import STDERR_LOG, error_line
from midas_cli.commands.root import COMMANDS, REGISTRY, ROOT_HELP
from midas_cli.errors import ConfigError, MidasError, SessionError, disk_full, disk_full_message

_state = {"debug": False}


def _version(value: bool) -> None:
    if value:
        sys.stdout.write(f"midas {__version__}\n")
        raise typer.Exit()


def _main(
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks and debug logging."),
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
) -> None:
    """The root options (its help is ``root.ROOT_HELP``)."""
    _state["debug"] = debug
    STDERR_LOG.setLevel(logging.DEBUG if debug else logging.WARNING)
    STDERR_LOG.setFormatter(logging.Formatter("midas: %(levelname)s %(name)s: %(message)s"))
    logging.getLogger().addHandler(STDERR_LOG)


def build_app(only: str | None = None) -> typer.Typer:
    """The CLI with every command, or with just ``only`` (what `run` uses, to import one module)."""
    app = typer.Typer(
        no_args_is_help=True,
        add_completion=True,
        pretty_exceptions_enable=False,
        context_settings={"help_option_names": ["-h", "--help"]},
    )
    app.callback(help=ROOT_HELP)(_main)
    for entry in REGISTRY:
        if only is not None and entry.name != only:
            continue
        target = getattr(importlib.import_module(f"midas_cli.commands.{entry.module}"), entry.attribute)
        if entry.kind == "group":
            app.add_typer(target, name=entry.name, hidden=entry.hidden)
        else:
            app.command(entry.name, hidden=entry.hidden)(target)
    return app


def _warn_if_renamed(name: str | None) -> None:
    """One warning line on stderr when ``name`` is an old spelling (it still runs, for a release)."""
    entry = COMMANDS.get(name or "")
    if entry is not None and entry.renamed_to:
        error_line(f"midas: warning: `midas {entry.name}` is now `{entry.renamed_to}` (the old name will go in a "
                   f"later release)")


def _invoked_command(argv: list[str]) -> str | None:
    first = next((arg for arg in argv if not arg.startswith("-")), None)
    return first if first in COMMANDS else None


def _usage_error(exc: Exception) -> int:
    """Click's usage error as one line plus a hint (click's own is a usage line and a 3-line box);
    returns its exit code (2). A command group run without arguments has printed its help already."""
    if type(exc).__name__ != "NoArgsIsHelpError":
        ctx = getattr(exc, "ctx", None)
        where = ctx.command_path if ctx is not None else "midas"
        command = where.removeprefix("midas").strip()
        message = " ".join(str(exc.format_message()).split())  # type: ignore[attr-defined]
        error_line(f"midas: error: {command + ': ' if command else ''}{message}")
        error_line(f"Try '{where} -h' for help.")
    return int(getattr(exc, "exit_code", 2))


def run() -> None:
    from typer._click.exceptions import ClickException, UsageError
    from typer.exceptions import Abort

    try:
        invoked = _invoked_command(sys.argv[1:])
        _warn_if_renamed(invoked)
        code = build_app(invoked)(prog_name="midas", standalone_mode=False)
        if isinstance(code, int) and code:  # typer.Exit(N) (no command returns a number)
            sys.exit(code)
    except UsageError as exc:
        sys.exit(_usage_error(exc))
    except ClickException as exc:
        error_line(f"midas: error: {' '.join(exc.format_message().split())}")
        sys.exit(exc.exit_code)
    except Abort:
        error_line("midas: interrupted")
        sys.exit(130)
    except KeyboardInterrupt:  # Ctrl-C before a command installed its own handling: no traceback
        error_line("midas: interrupted")
        sys.exit(130)
    except MidasError as exc:
        if _state["debug"]:
            traceback.print_exc()
        error_line(f"midas: error: {exc}")
        sys.exit(exc.exit_code)
    except Exception as exc:  # the one place that turns surprises into exit code 1
        if _state["debug"]:
            traceback.print_exc()
        if isinstance(exc, ModuleNotFoundError) and (exc.name or "").split(".")[0] == "torch":
            error_line(f"midas: error: {_invoked_command(sys.argv[1:]) or 'this command'} needs PyTorch, which "
                       f"this installation left out: pip install 'midas-cli[train]' (`make install` has it)")
            sys.exit(ConfigError.exit_code)
        full = disk_full(exc)
        if full is not None:  # not midas's bug: the disk is full or read-only, wherever it was hit
            error_line(f"midas: error: {disk_full_message(full)}")
            sys.exit(SessionError.exit_code)
        error_line(f"midas: internal error: {type(exc).__name__}: {exc} (run with --debug for a traceback)")
        sys.exit(1)
