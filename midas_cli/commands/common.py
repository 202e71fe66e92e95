"""Pieces shared by every command: consoles, --json output, error exit, number checks for options."""

from __future__ import annotations

import json
import logging
import math
import sys
from typing import Any, Callable, Optional

import typer
from typer.core import TyperOption

from midas_cli.console import stderr_console, stdout_console
from midas_cli.errors import ConfigError

err = stderr_console()
out = stdout_console()
STDERR_LOG = logging.StreamHandler(sys.stderr)  # library log records -> stderr (level set by --debug)


def _flag_shows_no_type(display_type_rich: Callable[..., Optional[str]]) -> Callable[..., Optional[str]]:
    """Typer's rich help gives every option a type column, so a flag (``--json``, ``--help``) reads
    ``--json <bool>`` as if it took a value. A flag takes none: leave its type column empty, as click's
    plain help does (counters like ``-v`` keep theirs)."""
    def display(self: TyperOption, ctx: typer.Context) -> Optional[str]:
        if self.is_flag and not self.count:
            return None
        return display_type_rich(self, ctx)
    display.__wrapped__ = display_type_rich  # type: ignore[attr-defined]
    return display


if not hasattr(TyperOption.display_type_rich, "__wrapped__"):
    TyperOption.display_type_rich = _flag_shows_no_type(TyperOption.display_type_rich)  # type: ignore[method-assign]



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
