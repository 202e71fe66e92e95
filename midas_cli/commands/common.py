"""Pieces shared by every command: consoles, --json output, error exit, number checks for options."""

from __future__ import annotations

import json
import logging
import math
import sys
from typing import Any, Callable, Optional

import typer

from midas_cli.console import stderr_console, stdout_console
from midas_cli.errors import ConfigError

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


# Number checks for float options, used as ``typer.Option(..., callback=positive)``. They run while the
# command line is parsed and raise ConfigError, so a bad value is one `midas: error: --fps ...` line and
# exit 2 before any work starts. ``None`` (an optional option not given) passes.
NumberCheck = Callable[[typer.CallbackParam, Optional[float]], Optional[float]]


def _number_check(accept: Callable[[float], bool], expected: str) -> NumberCheck:
    def check(param: typer.CallbackParam, value: Optional[float]) -> Optional[float]:
        if value is not None and not (math.isfinite(value) and accept(value)):
            name = max(param.opts, key=len) if param.opts else param.name
            raise ConfigError(f"{name} must be {expected}, got {value}")
        return value
    return check


finite = _number_check(lambda v: True, "a finite number")
positive = _number_check(lambda v: v > 0, "a finite number > 0")
non_negative = _number_check(lambda v: v >= 0, "a finite number >= 0")
probability = _number_check(lambda v: 0 <= v <= 1, "a probability between 0 and 1")
