"""The CLI surface: every command has --help with an example, errors are one line with the right code."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
import typer.main

from midas_cli.commands.main import build_app
from helpers.cli import REPO, midas


def _commands(group: typer.Typer, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    click_group = typer.main.get_group(group)
    found = []
    for name, command in click_group.commands.items():
        path = (*prefix, name)
        if command.hidden:  # an old spelling, kept for a release
            continue
        if hasattr(command, "commands"):
            found += [(*path, sub) for sub in command.commands]
        else:
            found.append(path)
    return found


ALL_COMMANDS = _commands(build_app())


def test_the_expected_commands_exist() -> None:
    assert {("record",), ("doctor",), ("session", "info"), ("session", "list"), ("session", "verify"),
            ("session", "repair")} <= set(ALL_COMMANDS)


@pytest.mark.parametrize("command", ALL_COMMANDS, ids=" ".join)
def test_every_command_has_help_with_an_example(command: tuple[str, ...]) -> None:
    result = midas(*command, "--help", check=True)
    assert "Usage: midas " + " ".join(command) in result.stdout
    assert "Example:" in result.stdout


@pytest.mark.parametrize("command", ALL_COMMANDS, ids=" ".join)
def test_every_command_is_documented_in_the_readme(command: tuple[str, ...]) -> None:
    assert f"midas {' '.join(command)}" in (REPO / "README.md").read_text()


def test_usage_error_exits_2_with_one_line() -> None:
    result = midas("record", "--duration", "5")
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0
    assert "nothing to record" in result.stderr


def test_bad_device_url_is_a_clear_usage_error(tmp_path: Path) -> None:
    result = midas("record", "--device", "emht=sim://emht?rate=240&bogus=1", "--subject", "1", "--task", "t",
                   "--trial", "1", "--out", str(tmp_path))
    assert result.returncode == 2
    assert "unknown parameter(s) bogus" in result.stderr
    assert not any(tmp_path.iterdir()), "no session folder may be created for a bad configuration"


def test_unknown_backend_is_refused_before_recording(tmp_path: Path) -> None:
    result = midas("record", "--device", "emht=nosuch:///dev/x", "--subject", "1", "--task", "t", "--trial", "1",
                   "--out", str(tmp_path))
    assert result.returncode == 2
    assert "not available" in result.stderr and "\n" not in result.stderr.strip()
    assert not any(tmp_path.iterdir())


def test_a_rig_whose_hardware_is_absent_fails_fast_with_exit_3(tmp_path: Path) -> None:
    """The shipped Raven-II rig, its fixed host resources (serial ports, OBS on 4455, UDP 36000 on every
    interface) moved to ones that are surely absent or free, so nothing else on the host is touched."""
    with socket.socket() as tcp, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        tcp.bind(("127.0.0.1", 0))
        udp.bind(("127.0.0.1", 0))
        obs_port, raven_port = tcp.getsockname()[1], udp.getsockname()[1]
    text = (REPO / "sessions_template/rigs/raven-ii.toml").read_text()
    for fixed, local in (("/dev/ttyUSB0", f"{tmp_path}/ttyUSB0"), ("/dev/ttyACM0", f"{tmp_path}/ttyACM0"),
                         ("obs://localhost:4455", f"obs://127.0.0.1:{obs_port}"),
                         ("raven://0.0.0.0:36000", f"raven://127.0.0.1:{raven_port}")):
        assert fixed in text, f"the template no longer says {fixed}: update this test"
        text = text.replace(fixed, local)
    rig = tmp_path / "raven-ii.toml"
    rig.write_text(text)
    result = midas("record", "--rig", str(rig), "--subject", "1", "--trial", "1", "--out", str(tmp_path / "out"),
                   "--no-tui")
    assert result.returncode == 3, result.stderr
    assert "could not open" in result.stderr.splitlines()[-1] or "ttyUSB0" in result.stderr.splitlines()[-1]


def test_session_errors_exit_4(tmp_path: Path) -> None:
    result = midas("session", "info", str(tmp_path))
    assert result.returncode == 4
    assert "not a midas session" in result.stderr


def test_doctor_reports_json() -> None:
    import json

    facts = json.loads(midas("doctor", "--json", check=True).stdout)
    assert facts["packages"]["numpy"] and "serial_ports" in facts and "cuda" in facts["gpu"]


def test_the_cli_starts_without_importing_heavy_libraries() -> None:
    """Every command pays for what the CLI imports at start: torch and cv2 load only where used."""
    import subprocess
    import sys

    code = ("import sys; sys.argv = ['midas', '--debug', 'record', '--help']\n"
            "from midas_cli.commands.main import run\n"
            "try:\n    run()\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in ('torch', 'cv2', 'scipy', 'matplotlib') if m in sys.modules))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert loaded.strip().splitlines()[-1] == "[]"
