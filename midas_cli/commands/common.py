"""Pieces shared by every command: consoles, --json output, error exit."""

from __future__ import annotations

import json
import logging
import sys
from typing import Any

import typer

from midas_cli.console import stderr_console, stdout_console

err = stderr_console()
out = stdout_console()
STDERR_LOG = logging.StreamHandler(sys.stderr)  # library log records -> stderr (level set by --debug)

JSON_OPTION = typer.Option(False, "--json", help="Print machine-readable JSON on stdout instead of a table.")


def print_json(data: Any) -> None:
    sys.stdout.write(json.dumps(data, indent=2, default=str) + "\n")
    sys.stdout.flush()


def error_line(message: str) -> None:
    """One unwrapped line on stderr (scripts grep it; a terminal wraps it itself)."""
    sys.stderr.write(" ".join(message.split("\n")) + "\n")
    sys.stderr.flush()


def fail(message: str, code: int) -> typer.Exit:
    """Print one error line to stderr and return the Exit to raise."""
    error_line(f"midas: error: {message}")
    return typer.Exit(code)
