"""`midas record --priority normal|high` (issue 26): the device workers' nice value, asked for, read back,
recorded; refused without permission (simulated in-process), a bad setting refused before recording."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import pytest

from midas_cli import config
from midas_cli.record import priority
from midas_cli.record.priority import HIGH_NICE, apply_priority, denied_warning, high_permitted
from helpers.cli import midas

META = ("--subject", "1", "--task", "suturing", "--trial", "1", "--duration", "2", "--no-tui")


def _config_env(tmp_path: Path, text: str) -> dict[str, str]:
    path = tmp_path / "config.toml"
    path.write_text(text)
    return {"MIDAS_CONFIG": str(path), "MIDAS_RIG": "", "MIDAS_SESSIONS": ""}


@pytest.fixture(scope="module")
def high_session(tmp_path_factory) -> tuple[Path, str]:
    """A 2 s simulated recording with --priority high over a config that says normal (the flag wins)."""
    if os.geteuid() != 0:
        pytest.skip("nice -10 needs root here (CI runs as root)")
    tmp = tmp_path_factory.mktemp("prio")
    env = _config_env(tmp, '[record]\npriority = "normal"\n')
    result = midas("record", "--simulate", "--priority", "high", "--out", str(tmp / "s"), *META, env=env, timeout=90)
    assert result.returncode == 0, result.stderr
    return Path(result.stdout.strip().splitlines()[-1]), result.stderr


def test_high_priority_workers_run_at_nice_minus_10_and_the_manifest_says_so(high_session) -> None:
    path, stderr = high_session
    manifest = json.loads((path / "manifest.json").read_text(encoding="utf-8"))
    assert os.getpriority(os.PRIO_PROCESS, 0) > HIGH_NICE  # so -10 can only be the workers' own doing
    for name in ("emht", "fps", "video", "handkp"):
        got = manifest["devices"][name]["priority"]
        assert got == {"asked": "high", "nice": HIGH_NICE, "got": "high"}, (name, got)
        assert manifest["sync"]["worker_priority"][name] == {"asked": "high", "got": "high", "nice": HIGH_NICE}
    assert "--priority high" not in stderr  # no refusal warning
    info = midas("session", "info", str(path), check=True).stdout
    assert "device emht: emht" in info and "priority high, nice -10" in info


def test_refused_high_priority_records_normal_and_says_how_to_allow_it(monkeypatch) -> None:
    before = os.getpriority(os.PRIO_PROCESS, 0)
    if before <= HIGH_NICE:
        pytest.skip("this test process already runs at nice -10 or below")

    def refuse(*_args: int) -> None:
        raise PermissionError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(os, "setpriority", refuse)
    result = apply_priority("high")
    assert result == {"asked": "high", "error": "Operation not permitted", "nice": before, "got": "normal"}
    warning = denied_warning({"emht": result, "fps": {**result}, "video": apply_priority("normal")})
    assert warning is not None and "\n" not in warning
    assert "emht, fps record at normal priority" in warning and "video" not in warning
    assert "Operation not permitted" in warning and "ulimit -e 30" in warning and "limits.conf" in warning


def test_the_nice_value_is_read_back_not_taken_from_the_request(monkeypatch) -> None:
    before = os.getpriority(os.PRIO_PROCESS, 0)
    if before <= HIGH_NICE:
        pytest.skip("this test process already runs at nice -10 or below")
    monkeypatch.setattr(os, "setpriority", lambda *_args: None)  # an OS that silently ignores the request
    assert apply_priority("high") == {"asked": "high", "nice": before, "got": "normal"}


def test_normal_priority_changes_nothing_and_warns_about_nothing(monkeypatch) -> None:
    def must_not_be_called(*_args: int) -> None:
        raise AssertionError("normal priority must not touch the nice value")

    monkeypatch.setattr(os, "setpriority", must_not_be_called)
    result = apply_priority("normal")
    assert result["asked"] == "normal" and result["nice"] == os.getpriority(os.PRIO_PROCESS, 0)
    assert denied_warning({"emht": result}) is None and denied_warning({}) is None


def test_high_permitted_names_its_reason_or_how_to_allow_it(monkeypatch, tmp_path) -> None:
    status = tmp_path / "status"
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    status.write_text("Name:\tpython\nCapEff:\t0000000000800000\n")  # bit 23: CAP_SYS_NICE
    assert high_permitted(status) == {"permitted": True, "by": "CAP_SYS_NICE", "how": ""}
    status.write_text("Name:\tpython\nCapEff:\tnot-hex\n")  # unreadable capabilities: not assumed
    monkeypatch.setattr(priority.resource, "getrlimit", lambda _which: (30, 30))  # ulimit -e 30: down to -10
    assert high_permitted(status)["by"] == "RLIMIT_NICE"
    monkeypatch.setattr(priority.resource, "getrlimit", lambda _which: (29, 30))  # only down to -9
    refused = high_permitted(status)
    assert refused["permitted"] is False and refused["by"] is None and "ulimit -e 30" in refused["how"]


def test_config_priority_is_the_default_and_a_bad_value_is_a_one_line_usage_error(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("MIDAS_CONFIG", str(tmp_path / "config.toml"))
    (tmp_path / "config.toml").write_text('[record]\npriority = "high"\n')
    assert config.default_priority() == "high"
    (tmp_path / "config.toml").write_text("[record]\n")
    assert config.default_priority() == "normal"
    env = _config_env(tmp_path, '[record]\npriority = "realtime"\n')
    result = midas("record", "--simulate", "--out", str(tmp_path / "s"), *META, env=env)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().count("\n") == 0 and "Traceback" not in result.stderr
    assert "[record] priority = 'realtime' is not one of normal, high" in result.stderr
    result = midas("record", "--simulate", "--priority", "urgent", "--out", str(tmp_path / "s"), *META,
                   env={"MIDAS_CONFIG": "", "XDG_CONFIG_HOME": str(tmp_path / "none")})
    assert result.returncode == 2 and "--priority must be one of normal, high, got 'urgent'" in result.stderr
    assert result.stderr.strip().count("\n") == 0
    assert not (tmp_path / "s").exists()  # nothing was recorded
