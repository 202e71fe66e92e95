"""Start-up (issue 17 goal 2): `midas --version` and `midas --help` import no command module and not typer;
`midas session info|list` imports none of numpy, pandas, scipy, torch, cv2, matplotlib; `midas <cmd> --help`
stays light where the command allows it. Behaviour, not timing: the timings are benchmarks/bench_startup.py.
The static root help (commands/root.py) is held to the real commands' help and to typer's own drawing."""

from __future__ import annotations

import inspect
import os
import re
import shlex
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

import pytest
import typer.main
from typer.testing import CliRunner

from midas_cli import __version__
from midas_cli.commands.main import build_app
from midas_cli.commands.root import COMMANDS, MIN_STATIC_WIDTH, REGISTRY, ROOT_HELP, listed, root_help
from helpers.cli import REPO, write_session

HEAVY = ("numpy", "pandas", "scipy", "torch", "cv2", "matplotlib", "pyarrow")


# Runs the CLI as `python -m midas_cli` does and writes every module loaded by the end to a file. (Not
# `-X importtime`: it does not see modules loaded through importlib.import_module, as build_app loads commands.)
_RUN = """import atexit, runpy, sys
def dump(path=sys.argv[1]):
    with open(path, "w") as fh:
        fh.write("\\n".join(sorted(sys.modules)))
atexit.register(dump)
sys.argv = ["midas", *sys.argv[2:]]
runpy.run_module("midas_cli", run_name="__main__", alter_sys=True)
"""


def _imported(*args: str, columns: int = 80) -> tuple[subprocess.CompletedProcess, set[str]]:
    """Run `python -m midas_cli ARGS`; the result and every module loaded by its end."""
    env = {**os.environ, "NO_COLOR": "1", "COLUMNS": str(columns)}
    with tempfile.TemporaryDirectory() as folder:
        listing = Path(folder) / "modules.txt"
        result = subprocess.run([sys.executable, "-c", _RUN, str(listing), *args], capture_output=True, text=True,
                                timeout=120, env=env, cwd=REPO)
        modules = set(listing.read_text().split("\n"))
    assert "midas_cli.commands.root" in modules, result.stderr[-2000:]
    return result, modules


def _top_level(modules: set[str]) -> set[str]:
    return {m.split(".")[0] for m in modules}


@pytest.mark.parametrize("args", [["--version"], ["--debug", "--version"]])
def test_version_imports_neither_typer_nor_any_command(args: list[str]) -> None:
    result, modules = _imported(*args)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout == f"midas {__version__}\n"
    assert not _top_level(modules) & {"typer", "rich", *HEAVY}
    assert not {m for m in modules if m.startswith("midas_cli.commands.")} - {"midas_cli.commands.root"}


@pytest.mark.parametrize("args", [["--help"], ["-h"], ["--debug", "--help"]])
def test_root_help_imports_neither_typer_nor_any_command(args: list[str]) -> None:
    result, modules = _imported(*args)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "Exit codes" in result.stdout and "extract" in result.stdout and "ground-truth" not in result.stdout
    assert not _top_level(modules) & {"typer", "rich", *HEAVY}
    assert not {m for m in modules if m.startswith("midas_cli.commands.")} - {"midas_cli.commands.root"}


def test_bare_midas_prints_the_help_and_exits_2_as_typer_does() -> None:
    result, modules = _imported()
    assert result.returncode == 2
    assert result.stdout == root_help(80).removesuffix("\n")
    assert "typer" not in _top_level(modules)


def test_narrow_terminals_get_typers_own_help() -> None:
    result, modules = _imported("--help", columns=MIN_STATIC_WIDTH - 1)
    assert result.returncode == 0 and "typer" in _top_level(modules)
    assert "Usage:" in result.stdout


@pytest.fixture(scope="module")
def small_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_session(tmp_path_factory.mktemp("startup"), rows=20)


@pytest.mark.parametrize("command", ["info", "list"])
def test_session_info_and_list_import_no_heavy_library(command: str, small_session: Path) -> None:
    target = small_session if command == "info" else small_session.parent
    result, modules = _imported("session", command, str(target))
    assert result.returncode == 0, result.stderr[-2000:]
    assert small_session.name in result.stdout
    assert not _top_level(modules) & set(HEAVY)


def test_session_verify_imports_no_scipy_torch_cv2_matplotlib(small_session: Path) -> None:
    result, modules = _imported("session", "verify", str(small_session))
    assert result.returncode == 0, result.stdout + result.stderr[-2000:]
    # numpy and pandas: the strict value parser (session/values.py) reads every line with them
    assert not _top_level(modules) & {"scipy", "torch", "cv2", "matplotlib"}


# `<cmd> --help` imports only the command's own module, and for these none of the heavy libraries.
# Not listed: record (the recorder), labels (pandas: EXPORT_FORMATS in its help), align (scipy: METHODS),
# calibrate (numpy: TARGETS), and train/features/extract/plot/doctor were already light.
LIGHT_HELP = ["session", "simulate", "import", "emulate", "eval", "export", "rig", "train", "extract", "plot",
              "doctor"]


@pytest.mark.parametrize("command", LIGHT_HELP)
def test_command_help_imports_only_its_module_and_no_heavy_library(command: str) -> None:
    result, modules = _imported(command, "--help")
    assert result.returncode == 0, result.stderr[-2000:]
    assert not _top_level(modules) & set(HEAVY), sorted(_top_level(modules) & set(HEAVY))
    own = f"midas_cli.commands.{COMMANDS[command].module}"
    commands = {m for m in modules if m.startswith("midas_cli.commands.")}
    assert own in commands
    others = {f"midas_cli.commands.{c.module}" for c in listed() if c.name != command}
    assert not commands & others


def _summary(command) -> str:
    """What typer lists for a command in its parent's help: short_help, else the first paragraph."""
    text = command.short_help or inspect.cleandoc(command.help or "").split("\n\n")[0]
    return " ".join(text.split())


def test_the_static_summaries_match_the_commands_own_help() -> None:
    root = typer.main.get_command(build_app())
    real = {name: _summary(command) for name, command in root.commands.items() if not command.hidden}
    summaries = {c.name: c.summary for c in listed()}
    assert summaries == real  # also the order: commands, then groups, as typer lists them
    assert list(summaries) == list(real)
    hidden = {name for name, command in root.commands.items() if command.hidden}
    assert hidden == {c.name for c in REGISTRY if c.renamed_to} and set(root.commands) == set(COMMANDS)
    assert inspect.cleandoc(root.help) == ROOT_HELP


@pytest.mark.parametrize("width", [MIN_STATIC_WIDTH, 63, 80, 100, 137, 200])
def test_the_static_root_help_is_drawn_as_typer_draws_it(width: int) -> None:
    result = CliRunner().invoke(build_app(), ["--help"], env={"COLUMNS": str(width)}, prog_name="midas")
    assert result.exit_code == 0
    assert root_help(width) == result.output


def test_the_fast_path_prints_the_static_help(tmp_path: Path) -> None:
    env = {**os.environ, "COLUMNS": "100", "NO_COLOR": "1"}
    result = subprocess.run([sys.executable, "-m", "midas_cli", "--help"], capture_output=True, text=True,
                            timeout=120, env=env, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout == root_help(100)


# As if torch were not installed (the console laptop's `pip install midas-cli`, no [train] extra).
_NO_TORCH = """import runpy, sys
sys.modules["torch"] = None
sys.argv = ["midas", *sys.argv[1:]]
runpy.run_module("midas_cli", run_name="__main__", alter_sys=True)
"""


def _without_torch(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _NO_TORCH, *args], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "NO_COLOR": "1"})


def test_recording_needs_no_torch_and_training_says_how_to_get_it(tmp_path: Path) -> None:
    """torch is the `train` extra: record, verify and export run without it; a command that needs it is one
    line naming the extra, exit 2 (it was an internal error)."""
    made = _without_torch("record", "--simulate", "--duration", "1", "--no-tui", "--out", str(tmp_path / "s"),
                          "--subject", "1", "--task", "t", "--trial", "1")
    assert made.returncode == 0, made.stderr
    session = made.stdout.strip().splitlines()[-1]
    assert _without_torch("session", "verify", session).returncode == 0
    assert _without_torch("export", session, "--format", "parquet", "--out", str(tmp_path / "x")).returncode == 0
    train = _without_torch("train", "gestures", session, "--out", str(tmp_path / "run"))
    lines = train.stderr.strip().splitlines()
    assert train.returncode == 2 and len(lines) == 1, train.stderr
    assert "PyTorch" in lines[0] and "pip install 'midas-cli[train]'" in lines[0]
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("words, cword, expected", [
    ("midas exp", 1, "export"), ("midas session ve", 2, "verify"), ("midas export --fo", 2, "--format"),
    ("midas ext", 1, "extract"), ("midas extract im", 2, "image-features")])
def test_shell_completion_answers_from_the_commands(words: str, cword: int, expected: str) -> None:
    """Completion was switched off; bash's request (what `midas --install-completion` wires up) is
    answered from the real commands, not by the static root help."""
    env = {**os.environ, "COMP_WORDS": words, "COMP_CWORD": str(cword), "_MIDAS_COMPLETE": "complete_bash"}
    result = subprocess.run([sys.executable, "-m", "midas_cli"], capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == [expected]


def test_completion_script_is_offered() -> None:
    # typer finds the user's shell from the parent process: run it from bash, as a user's terminal does
    # (CI's own parent is sh, which typer does not support). `; true` keeps bash from exec-ing python.
    command = f"{shlex.quote(sys.executable)} -m midas_cli --show-completion; true"
    result = subprocess.run(["bash", "-c", command], capture_output=True, text=True, timeout=120)
    assert "_MIDAS_COMPLETE=complete_bash" in result.stdout, result.stderr
    # the script is also reachable without any shell detection, the way click documents it
    env = {**os.environ, "_MIDAS_COMPLETE": "source_bash"}
    result = subprocess.run([sys.executable, "-m", "midas_cli"], capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 0 and "_MIDAS_COMPLETE=complete_bash" in result.stdout, result.stderr


def test_install_completion_wires_bash_to_the_commands(tmp_path: Path) -> None:
    """`midas --install-completion` (from bash, as a user's terminal runs it) writes a script that
    ~/.bashrc sources; that script, as bash calls it for `midas exp<TAB>`, completes `export`."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "midas").write_text(f'#!/bin/sh\nexec {shlex.quote(sys.executable)} -m midas_cli "$@"\n')
    (bin_dir / "midas").chmod(0o755)
    env = {**os.environ, "HOME": str(tmp_path), "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    installed = subprocess.run(["bash", "-c", "midas --install-completion; true"], capture_output=True, text=True,
                               env=env, timeout=120)
    assert "bash completion installed" in installed.stdout, installed.stderr
    tab = ('source ~/.bashrc; COMP_WORDS=(midas exp); COMP_CWORD=1; _midas_completion midas; '
           'printf "%s\\n" "${COMPREPLY[@]}"')
    completed = subprocess.run(["bash", "-c", tab], capture_output=True, text=True, env=env, timeout=120)
    assert completed.stdout.split() == ["export"], completed.stderr


def test_torch_is_only_in_the_train_extra_and_make_installs_it() -> None:
    """`pip install midas-cli` (the console laptop) pulls no torch; `[train]` does, and `make demo`/`make
    test` install it with the dev tools."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    names = [re.split(r"[<>=!~\[ ;]", d, maxsplit=1)[0].lower() for d in project["dependencies"]]
    assert not any(n.startswith("torch") for n in names), names
    assert any(d.startswith("torch") for d in project["optional-dependencies"]["train"])
    assert "-e '.[dev,train]'" in (REPO / "Makefile").read_text()
