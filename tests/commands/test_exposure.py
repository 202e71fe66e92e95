"""Exposure nobody chose: credentials in device URLs and rig files are refused without being echoed, a
URL is shown redacted wherever it is shown, and the liblsl configuration that applies to midas's LSL
outlets is the one liblsl itself loads."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from midas_cli.devices.base import DeviceUrl, is_secret_key, redact_url
from midas_cli.devices.lsl.outlet import exposure_note, lsl_config_file
from midas_cli.devices.obs.connection import resolve_password
from midas_cli.devices.registry import describe_device
from midas_cli.devices.rigconfig import parse_rig
from midas_cli.errors import ConfigError
from helpers.cli import midas

SECRET = "Hunter2-not-for-logs"
META = ("--subject", "1", "--task", "t", "--trial", "1", "--no-tui", "--duration", "1")


@pytest.mark.parametrize("device", [
    f"video=obs://{SECRET}@127.0.0.1:4455",
    f"video=obs://127.0.0.1:4455?fps=30&pw={SECRET}",
    f"video=obs://127.0.0.1:4455?Password={SECRET}",
    f"obs://user:{SECRET}@127.0.0.1:4455",  # no NAME=: the usage error shows the URL redacted too
], ids=["user-part", "pw", "Password", "no-name"])
def test_credentials_in_a_device_url_are_refused_without_echo(tmp_path: Path, device: str) -> None:
    result = midas("record", "--device", device, "--out", str(tmp_path), *META)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("midas: error: ")
    assert SECRET not in result.stdout + result.stderr
    assert "***" in result.stderr
    assert list(tmp_path.iterdir()) == []  # refused before a session (its manifest) existed


def test_a_rig_file_password_is_refused_naming_where_it_goes(tmp_path: Path) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text(f'[rig]\nname = "r"\nplatform = "p"\n[devices.video]\nurl = "obs://127.0.0.1:4455"\n'
                   f'password = "{SECRET}"\n', encoding="utf-8")
    result = midas("record", "--rig", str(rig), "--out", str(tmp_path / "out"), *META)
    assert result.returncode == 2 and result.stderr.count("\n") == 1
    assert f"{rig}: devices.video.password: a rig file holds no passwords" in result.stderr
    assert "MIDAS_OBS_PASSWORD" in result.stderr and "password_env" in result.stderr
    assert SECRET not in result.stdout + result.stderr and not (tmp_path / "out").exists()


@pytest.mark.parametrize("url", [
    f"raven://u:{SECRET}@0.0.0.0:36000", f"lsl://?name=hr&api_token={SECRET}", f"fps:///dev/ttyACM0?PWD={SECRET}",
    f"sim://emht?Secret={SECRET}", f"fob://{SECRET}@/dev/ttyUSB0", f"obs://[{SECRET}@127.0.0.1",
    f"{SECRET}@host", f"obs://127.0.0.1?%70w={SECRET}", f"obs://u:{SECRET}/x@host:4455",
    f"obs://u:{SECRET}?x@host:4455&fps=30", f" obs://{SECRET}@host",
], ids=["raven", "lsl", "fps", "sim", "fob", "bad-ipv6", "no-scheme", "percent-encoded-key", "slash-in-password",
        "question-mark-in-password", "leading-space"])
def test_every_scheme_refuses_credentials_without_echo(url: str) -> None:
    with pytest.raises(ConfigError) as error:
        DeviceUrl.parse(url)
    assert SECRET not in str(error.value)


def test_parameters_that_name_where_a_secret_is_are_not_secrets() -> None:
    url = DeviceUrl.parse("obs://127.0.0.1:4455?fps=30&password_env=OBS_PW&marker=Sync")
    assert url.params["password_env"] == "OBS_PW" and url.redacted() == url.raw
    assert DeviceUrl.parse("lsl://?name=lab@site").params == {"name": "lab@site"}
    assert not any(is_secret_key(key) for key in ("password_env", "compass", "marker", "source_id", "hostname"))
    assert all(is_secret_key(key) for key in ("password", "PW", "Passwd", "api_token", "obs.secret", "key"))


@pytest.mark.parametrize(("text", "shown"), [
    (f"obs://user:{SECRET}@host:4455?fps=30", "obs://***@host:4455?fps=30"),
    (f"obs://host?fps=30&Password={SECRET}&marker=m", "obs://host?fps=30&Password=***&marker=m"),
    (f"{SECRET}@host/path?token={SECRET}", "***@host/path?token=***"),
    (f"obs://[{SECRET}@h:1", "obs://***@h:1"),
    (f"obs://u:{SECRET}?x@host:4455&fps=30", "obs://***@host:4455&fps=30"),
    ("lsl://?name=lab@site&rate=10", "lsl://?name=lab@site&rate=10"),  # an '@' in a value is no user part
    ("sim://emht?rate=240", "sim://emht?rate=240"),
    ("fob:///dev/ttyUSB0?baud=115200", "fob:///dev/ttyUSB0?baud=115200"),
])
def test_redact_url_hides_user_parts_and_secret_values(text: str, shown: str) -> None:
    assert redact_url(text) == shown


def test_redact_url_never_raises_on_odd_text() -> None:
    for text in ("", "@", "://", "?", "a://@?=&", "\x00\n", "obs://h?=x&&pw", "[", "x" * 10_000 + "@h"):
        assert isinstance(redact_url(text), str)


def test_the_lsl_config_is_the_file_liblsl_loads(tmp_path: Path, monkeypatch) -> None:
    home, work = tmp_path / "home", tmp_path / "work"
    (home / "lsl_api").mkdir(parents=True)
    work.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(work)
    in_home = home / "lsl_api" / "lsl_api.cfg"
    in_home.write_text("[multicast]\nResolveScope = machine\n")
    assert lsl_config_file({}) == in_home  # no ./lsl_api.cfg: the home folder's
    (work / "lsl_api.cfg").write_text("[ports]\nIPv6 = disable\n")
    assert lsl_config_file({}) == work / "lsl_api.cfg"  # the working folder's comes before it
    named = tmp_path / "named.cfg"
    named.write_text("[lab]\n")
    assert lsl_config_file({"LSLAPICFG": str(named)}) == named  # $LSLAPICFG first of all
    assert lsl_config_file({"LSLAPICFG": str(tmp_path / "missing.cfg")}) == work / "lsl_api.cfg"
    assert str(named) in exposure_note(named) and "every network interface" in exposure_note(named)
    assert "liblsl's defaults" in exposure_note(None)


def test_an_obs_password_file_only_its_owner_can_read_is_used(tmp_path: Path) -> None:
    secret_file = tmp_path / "obs.pw"
    secret_file.write_text(f"{SECRET}\n", encoding="utf-8")
    secret_file.chmod(0o600)
    assert resolve_password("", str(secret_file)) == (SECRET, f"file {secret_file}")
    secret_file.chmod(0o640)
    with pytest.raises(ConfigError, match="may be read by others .*chmod 600") as error:
        resolve_password("", str(secret_file))
    assert SECRET not in str(error.value)
    with pytest.raises(ConfigError, match="not both"):
        resolve_password("OBS_PW", str(secret_file))


@pytest.mark.parametrize("make", [lambda p: p.write_bytes(b""), lambda p: p.mkdir(), lambda p: os.mkfifo(p),
                                  lambda p: None], ids=["empty", "folder", "fifo", "missing"])
def test_an_unusable_obs_password_file_is_one_clear_error(tmp_path: Path, make) -> None:
    path = tmp_path / "obs.pw"
    make(path)
    if path.exists():
        path.chmod(0o600)
    with pytest.raises(ConfigError, match=f"OBS password file {path}"):
        resolve_password("", str(path))  # a FIFO never blocks it


def test_a_rig_password_file_reaches_the_device_relative_to_the_rig(tmp_path: Path) -> None:
    rig = parse_rig({"rig": {"name": "r", "platform": "p"},
                     "devices": {"video": {"url": "obs://localhost:4455", "password_file": "secrets/obs.pw"}}},
                    str(tmp_path / "rig.toml"))
    url = rig.device_urls()["video"]
    assert describe_device("video", url).settings()["password_file"] == str(tmp_path / "secrets" / "obs.pw")
    assert not is_secret_key("password_file") and DeviceUrl.parse(url).redacted() == url
