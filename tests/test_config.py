"""Defaults a technician sets once (issue 15 item 7): MIDAS_RIG, MIDAS_SESSIONS and config.toml, through the CLI."""

from __future__ import annotations

import json
from pathlib import Path

from helpers.cli import REPO, midas

RIG = REPO / "sessions_template" / "rigs" / "simulated.toml"
META = ["--subject", "1", "--task", "suturing", "--trial", "1", "--duration", "2", "--no-tui"]


def isolated(tmp_path: Path, **extra: str) -> dict[str, str]:
    """An environment with its own XDG config folder and no technician defaults inherited from the caller."""
    return {"XDG_CONFIG_HOME": str(tmp_path / "xdg"), "MIDAS_RIG": "", "MIDAS_SESSIONS": "", "MIDAS_CONFIG": "",
            **extra}


def write_config(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "xdg" / "midas" / "config.toml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_record_uses_the_environments_rig_and_sessions_folder_and_list_and_info_follow(tmp_path):
    sessions = tmp_path / "data" / "sessions"
    env = isolated(tmp_path, MIDAS_RIG=str(RIG), MIDAS_SESSIONS=str(sessions))
    result = midas("record", *META, cwd=tmp_path, env=env)
    assert result.returncode == 0, result.stderr
    [session] = list(sessions.iterdir())
    assert result.stdout.strip().splitlines()[-1] == str(session)
    manifest = json.loads((session / "manifest.json").read_text())
    assert manifest["rig"]["source"].endswith("simulated.toml")  # the rig file, not the built-in rig
    assert not (tmp_path / "sessions").exists()

    listed = midas("session", "list", "--paths", cwd=tmp_path, env=env)  # no ROOT: MIDAS_SESSIONS
    assert listed.returncode == 0, listed.stderr
    assert listed.stdout.split() == [str(session)]

    info = json.loads(midas("session", "info", str(session), "--json", env=env, check=True).stdout)
    recorded = [name for name, stream in info["streams"].items() if stream["samples"]]
    assert recorded, "a 2-s recording holds rows of at least one stream, however busy the machine"
    for name, stream in info["streams"].items():
        entry = manifest["streams"][name]
        assert stream["first_t_host_ns"] == entry["first_t_host_ns"] and stream["last_t_host_ns"] == entry["last_t_host_ns"]
        if name in recorded:
            assert 0 <= stream["first_s"] <= stream["last_s"]
            assert stream["last_s"] == round((entry["last_t_host_ns"] - manifest["start"]["host_ns"]) / 1e9, 6)
        else:
            assert stream["first_s"] is None and stream["last_s"] is None
    table = midas("session", "info", str(session), env=env, check=True).stdout
    assert "first s" in table and "last s" in table


def test_config_file_gives_defaults_the_environment_and_flags_override(tmp_path):
    write_config(tmp_path, f'[record]\nrig = "{RIG}"\nsessions = "from-config"\n[slurm]\npartition = "debug"\n')
    env = isolated(tmp_path)
    shown = json.loads(midas("config", "--json", env=env, check=True).stdout)
    assert shown["sessions"]["value"] == str(tmp_path / "xdg" / "midas" / "from-config")  # relative to the file
    assert shown["rig"]["source"].endswith("config.toml [record]") and shown["slurm"] == {"partition": "debug"}

    shown = json.loads(midas("config", "--json", env={**env, "MIDAS_SESSIONS": "/elsewhere"}, check=True).stdout)
    assert shown["sessions"] == {"value": "/elsewhere", "source": "MIDAS_SESSIONS"}

    flag_out = tmp_path / "flag-out"
    result = midas("record", *META, "--out", str(flag_out), cwd=tmp_path, env=env)
    assert result.returncode == 0, result.stderr
    assert len(list(flag_out.iterdir())) == 1 and not (tmp_path / "xdg" / "midas" / "from-config").exists()


def test_bad_config_and_missing_defaults_are_one_line_usage_errors(tmp_path):
    env = isolated(tmp_path)
    result = midas("record", "--subject", "1", "--task", "t", "--trial", "1", cwd=tmp_path, env=env)
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "MIDAS_RIG" in result.stderr
    assert not (tmp_path / "sessions").exists()

    write_config(tmp_path, '[record]\nsesions = "x"\n')
    result = midas("record", *META, cwd=tmp_path, env=env)
    assert result.returncode == 2 and "unknown key 'sesions' in [record]" in result.stderr
    assert result.stderr.strip().count("\n") == 0

    write_config(tmp_path, '[slurm]\ngpus = "two"\n')
    result = midas("config", env=env)
    assert result.returncode == 2 and "[slurm] gpus = 'two' should be a int" in result.stderr

    write_config(tmp_path, '[record\n')
    result = midas("session", "list", env=env)
    assert result.returncode == 2 and "not valid TOML" in result.stderr

    result = midas("config", env={**env, "MIDAS_CONFIG": str(tmp_path / "nope.toml")})
    assert result.returncode == 2 and "no such config file" in result.stderr
