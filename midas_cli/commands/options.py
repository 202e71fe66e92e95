"""Options and arguments that several commands share, defined once, with one meaning per name.

Names and what they always mean:

* ``SESSION_ARG``: one session folder (holds manifest.json).
* ``SESSIONS_ARG``: one or more session folders.
* ``ALIGNED_SESSIONS_ARG``: session folders `midas align` has run on (derived/aligned.*).
* ``KINEMATIC_SESSIONS_ARG``: session folders with robot kinematics (mtm/psm streams), one per trial.
* ``SESSION_TREES_ARG``: session folders, or folders holding sessions (searched 3 levels deep).
* ``--json`` (``JSON_OPTION``): machine-readable JSON on stdout instead of a table.
* ``--rate``: a device's own sample rate (the emulators). The frame rate of an aligned table is
  ``align --downsample``; the rate the gesture models see is ``train --model-rate``.
* ``--model``: which gesture model ``train`` trains; the calibration model ``align`` and ``eval``
  use is ``--calibration-model``.
* ``--device``: a rig device, by name (``calibrate fps``, ``extract handkp``) or defined as NAME=URL
  (``record``). Where torch computes (cpu or cuda) is ``--accelerator`` (``train``, ``extract
  image-features``); ``--device`` there is its old name, kept for a release.
* ``fps`` is the foot-pedal board (the device kind, ``fps://``); a video's frame rate is
  ``--frame-rate`` (``labels stats``, ``simulate console-video``; ``--fps`` there is its old name).
* Options that always travel together are declared once as a group (``option_group``: the executor
  options of every batch command) and reach the command as one object.
* ``--split``: how ``train`` splits sessions into train/test; ``import midas-dcs`` cutting a folder into
  one session per recording is ``--split-recordings`` (``--split`` there is its old name).
"""

from __future__ import annotations

import functools
import inspect
from typing import Any, Callable, Optional, Sequence

import typer

from midas_cli.commands.common import error_line, positive
from midas_cli.errors import ConfigError

JSON_OPTION = typer.Option(False, "--json", help="Print machine-readable JSON on stdout instead of a table.")

SESSION_ARG = typer.Argument(..., help="Session folder (holds manifest.json).")
SESSIONS_ARG = typer.Argument(..., help="Session folder(s).", file_okay=False)
ALIGNED_SESSIONS_ARG = typer.Argument(..., help="Aligned session folder(s) (run `midas align` first).",
                                      file_okay=False)
KINEMATIC_SESSIONS_ARG = typer.Argument(..., help="Session folder(s) with robot kinematics (each is one trial).",
                                        file_okay=False)
SESSION_TREES_ARG = typer.Argument(..., help="Session folders, or folders holding sessions (searched 3 levels "
                                   "deep).")


ACCELERATOR_OPTION = typer.Option(None, "--accelerator", help="Where torch computes: cpu (default) or cuda.")


def renamed_option(old: str, new: str, callback: Optional[Callable] = positive) -> typer.models.OptionInfo:
    """A hidden option under a flag's old name, still accepted for a release (see ``take_renamed``);
    ``callback`` checks its value as the new option's does (numbers: ``positive``; None: no check)."""
    return typer.Option(None, old, hidden=True, callback=callback, help=f"Old name of {new}.")


OLD_ACCELERATOR_OPTION = renamed_option("--device", "--accelerator", callback=None)


def accelerator(accelerator_name: Optional[str], old_device: Optional[str]) -> str:
    """The torch device ``--accelerator`` names (or its old name ``--device``, with a warning); cpu when
    neither is given."""
    return take_renamed(accelerator_name, old_device, "--device", "--accelerator", error_line) or "cpu"


def take_renamed(value, old_value, old: str, new: str, warn: Callable[[str], None]):
    """The value given under ``new``, or under its old name ``old`` (with a warning, via ``warn``);
    both at once is a usage error."""
    if old_value is None:
        return value
    if value is not None:
        raise ConfigError(f"{old} is the old name of {new}: give only {new}")
    warn(f"midas: warning: {old} is now {new} (the old name will go in a later release)")
    return old_value


def keyword_options(*specs: tuple[str, Any, Any]) -> tuple[inspect.Parameter, ...]:
    """(name, typer option, annotation) triples as keyword-only parameters, for ``option_group``."""
    return tuple(inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=option, annotation=annotation)
                 for name, option, annotation in specs)


def option_group(name: str, factory: Callable[..., Any],
                 parameters: Sequence[inspect.Parameter]) -> Callable[[Callable[..., None]], Callable[..., None]]:
    """A decorator for options several commands share, declared once (the sqlite-utils ``output_options``
    way): the command's signature, which typer reads, gets ``parameters`` after its own, and the command
    is called with their values bundled as one keyword argument ``name`` = ``factory(**values)``."""
    def declare(command: Callable[..., None]) -> Callable[..., None]:
        own = [p for key, p in inspect.signature(command).parameters.items() if key != name]

        @functools.wraps(command)
        def run(**given: Any) -> None:
            bundle = factory(**{p.name: given.pop(p.name) for p in parameters})
            command(**given, **{name: bundle})

        signature = inspect.Signature([*own, *parameters])
        run.__signature__ = signature  # type: ignore[attr-defined]
        run.__annotations__ = {p.name: p.annotation for p in signature.parameters.values()}
        return run
    return declare


# Declares a command that runs torch: --accelerator (and its old name) reach it as one ``device: str``.
accelerator_option = option_group("device", accelerator, keyword_options(
    ("accelerator_name", ACCELERATOR_OPTION, Optional[str]), ("old_device", OLD_ACCELERATOR_OPTION, Optional[str])))
