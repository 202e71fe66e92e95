"""Rig files: the templates validate, unknown keys are refused, secrets never reach a manifest."""

from __future__ import annotations

from pathlib import Path

import pytest

from midas_cli.devices.rigconfig import load_rig, parse_rig
from midas_cli.errors import ConfigError
from midas_cli.rig import simulated_rig
from helpers.cli import REPO

TEMPLATES = sorted((REPO / "sessions_template" / "rigs").glob("*.toml"))


def test_there_are_three_rig_templates() -> None:
    assert {p.stem for p in TEMPLATES} == {"simulated", "raven-ii", "davinci-xi"}


@pytest.mark.parametrize("path", TEMPLATES, ids=lambda p: p.stem)
def test_templates_validate(path: Path) -> None:
    rig = load_rig(path)
    assert rig.devices and rig.platform


def test_simulated_template_matches_the_built_in_rig() -> None:
    template = load_rig(REPO / "sessions_template/rigs/simulated.toml")
    assert template.device_urls() == simulated_rig().device_urls()
    assert template.platform == simulated_rig().platform


def test_unknown_key_is_named() -> None:
    with pytest.raises(ConfigError, match="unknown key devices.emht.rate"):
        parse_rig({"rig": {"name": "r", "platform": "p"}, "devices": {"emht": {"url": "sim://emht", "rate": 3}}},
                  "x.toml")


def test_wrong_type_is_refused() -> None:
    with pytest.raises(ConfigError, match="rig.master_rate_hz has the wrong type"):
        parse_rig({"rig": {"name": "r", "platform": "p", "master_rate_hz": "fast"},
                   "devices": {"emht": {"url": "sim://emht"}}}, "x.toml")


@pytest.mark.parametrize("device", [{"url": "obs://localhost:4455", "password": "s3cret"},
                                    {"url": "obs://localhost:4455", "Obs_PW": "s3cret"},
                                    {"url": "obs://user:s3cret@localhost:4455"},
                                    {"url": "obs://localhost:4455?password=s3cret"}],
                         ids=["password-key", "pw-key-any-case", "url-user-part", "url-parameter"])
def test_a_secret_in_a_rig_file_is_refused_naming_where_it_goes(device: dict) -> None:
    with pytest.raises(ConfigError) as error:
        parse_rig({"rig": {"name": "r", "platform": "p"}, "devices": {"video": device}}, "x.toml")
    message = str(error.value)
    assert "s3cret" not in message
    assert message.startswith("x.toml: devices.video.") and "MIDAS_OBS_PASSWORD" in message
