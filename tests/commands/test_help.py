"""Help text: a one-line summary then a blank line everywhere, the exit codes in `midas --help`, flags shown
as flags (issue 18 item 6)."""

from __future__ import annotations

import inspect
import os
import subprocess
import sys

import pytest
import typer.main
from typer.testing import CliRunner

from midas_cli.commands.main import build_app
from helpers.cli import REPO

SUMMARY_MAX = 80


def _tree(command, path: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], object]]:
    """Every command and group under ``command`` (the root included), with its path."""
    found = [(path, command)]
    for name, sub in getattr(command, "commands", {}).items():
        found += _tree(sub, (*path, name))
    return found


TREE = _tree(typer.main.get_command(build_app()))
LEAVES = [path for path, command in TREE if not hasattr(command, "commands")]


def test_the_tree_has_every_leaf_command() -> None:
    assert len(LEAVES) >= 31
    assert ("calibrate", "fps") in LEAVES and ("record",) in LEAVES


@pytest.mark.parametrize(("path", "command"), TREE, ids=[" ".join(("midas", *p)) for p, _ in TREE])
def test_help_opens_with_one_summary_line_then_a_blank_line(path: tuple[str, ...], command) -> None:
    lines = inspect.cleandoc(command.help or "").split("\n")
    assert lines[0].strip(), f"midas {' '.join(path)}: no help text"
    assert len(lines[0]) <= SUMMARY_MAX, f"midas {' '.join(path)}: summary is {len(lines[0])} characters"
    assert len(lines) == 1 or lines[1] == "", f"midas {' '.join(path)}: the summary runs onto a second line"


@pytest.mark.parametrize("path", [p for p, _ in TREE], ids=[" ".join(("midas", *p)) for p, _ in TREE])
def test_flags_are_not_shown_as_bool_values(path: tuple[str, ...]) -> None:
    result = CliRunner().invoke(build_app(), [*path, "--help"], env={"COLUMNS": "100", "NO_COLOR": "1"})
    assert result.exit_code == 0, result.output
    assert "Usage:" in result.output
    assert "<bool>" not in result.output
    assert "--help" in result.output


def test_root_help_shows_the_exit_codes() -> None:
    env = {**os.environ, "COLUMNS": "100", "NO_COLOR": "1"}
    result = subprocess.run([sys.executable, "-m", "midas_cli", "--help"], capture_output=True, text=True,
                            timeout=120, env=env, cwd=REPO)
    assert result.returncode == 0, result.stderr
    assert "Exit codes" in result.stdout
    assert "0 ok, 1 internal, 2 usage, 3 device, 4 session/data" in result.stdout
    assert "record and analyse multimodal data" in result.stdout
    assert "<bool>" not in result.stdout
