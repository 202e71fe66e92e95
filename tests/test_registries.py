"""One registry per extension point (issue 25): gesture models (models/registry.py), device backends
(devices/registry.py) and export formats (interop/export.py). Each table is the single source: every entry
is complete and consistent with the code it names, the CLI's choices and help are its names, and reading a
table imports none of the modules it names."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import asdict

import pytest
import torch
import typer.main

from midas_cli.commands.main import build_app
from midas_cli.devices.base import Device, DeviceUrl
from midas_cli.devices.registry import BACKENDS, KINDS, SCHEMES, backend_entry, create_device
from midas_cli.devices.rigconfig import parse_rig
from midas_cli.errors import ConfigError
from midas_cli.interop.export import EXPORT_FORMATS, FORMATS, parse_formats
from midas_cli.models.registry import ENTRIES, MODELS, model_entry
from midas_cli.models.train import RECIPES, SELECTIONS, TrainConfig, build_model
from helpers.cli import REPO

ROOT = typer.main.get_command(build_app())


def _option_help(path: tuple[str, ...], flag: str) -> str:
    """The help of option ``flag`` of `midas PATH`, as typer shows it."""
    command = ROOT
    for name in path:
        command = command.commands[name]
    return next(p.help for p in command.params if flag in getattr(p, "opts", ()))


def _names_in(help_text: str) -> list[str]:
    """The choices a help lists: ``a (what), b, c or d.`` / ``a, b and/or c (...)`` -> [a, b, c, d]."""
    words = help_text.split(" (repeat")[0].rstrip(".").replace(" and/or ", ", ").replace(" or ", ", ")
    return [item.split(" (")[0].strip() for item in words.split(", ")]


# --- models ---

@pytest.mark.parametrize("entry", ENTRIES, ids=[e.name for e in ENTRIES])
def test_every_model_builds_and_has_a_recipe_and_a_title(entry) -> None:
    network, config = build_model(entry.name, {"emht": 3, "image": 2}, 4, {})
    assert isinstance(network, torch.nn.Module)
    mask = torch.ones(1, 12, dtype=torch.bool)
    logits = network.frame_logits(network(torch.randn(1, 5, 12), mask))
    assert logits.shape == (1, 4, 12)  # (B, classes, T): the entry's builder saw the dims and class count
    assert config["n_classes"] == 4
    assert RECIPES[entry.name] == asdict(entry.recipe)
    for name, recipe in _trained_recipes(entry, config):
        assert recipe.epochs > 0 and recipe.batch_size > 0 and recipe.lr > 0
        assert recipe.selection in SELECTIONS
        resolved = TrainConfig(model=name).resolved()
        assert (resolved.epochs, resolved.lr) == (recipe.epochs, recipe.lr)
    assert entry.title


def _trained_recipes(entry, config: dict) -> list:
    """(model, recipe) of the networks the entry trains: its own, or an ensemble's members' (its own
    leaves epochs, batch size and lr to them; its selection, where it has one, applies to every member)."""
    if "members" not in config:
        return [(entry.name, entry.recipe)]
    assert (entry.recipe.epochs, entry.recipe.batch_size, entry.recipe.lr) == (None,) * 3
    assert entry.recipe.selection is None or entry.recipe.selection in SELECTIONS
    return [(m, MODELS[m].recipe) for m in config["members"]]


def test_model_names_and_titles_are_unique() -> None:
    assert len(MODELS) == len(ENTRIES)
    assert len({e.title for e in ENTRIES}) == len(ENTRIES)  # an ablation table tells the models apart


def test_model_help_lists_exactly_the_registry() -> None:
    help_text = _option_help(("train", "gestures"), "--model")
    assert _names_in(help_text) == list(MODELS)
    assert "mstcn (MS-TCN++)" in help_text


@pytest.mark.parametrize("build", [lambda: model_entry("tcn"), lambda: TrainConfig(model="tcn"),
                                   lambda: build_model("tcn", {"emht": 3}, 4, {})])
def test_an_unknown_model_is_refused_naming_the_known_ones(build) -> None:
    with pytest.raises(ConfigError, match="'tcn' is unknown") as caught:
        build()
    assert all(name in str(caught.value) for name in MODELS)


# --- device backends ---

@pytest.mark.parametrize("entry", BACKENDS, ids=[f"{b.scheme}-{b.simulated}" if b.simulated else b.scheme
                                                 for b in BACKENDS])
def test_every_backend_loads_a_device_class_of_its_kind(entry) -> None:
    assert entry.module.startswith("midas_cli.devices.")  # the registry's imports stay in the devices layer
    backend = entry.load()
    assert issubclass(backend, Device)
    assert backend.kind == entry.kind and entry.kind in KINDS
    url = f"sim://{entry.simulated}" if entry.scheme == "sim" else f"{entry.scheme}://x"
    assert backend_entry(DeviceUrl.parse(url)) is entry


def test_schemes_and_kinds_come_from_the_entries() -> None:
    assert set(SCHEMES) == {b.scheme for b in BACKENDS} and set(KINDS) == {b.kind for b in BACKENDS}
    real = [b.scheme for b in BACKENDS if b.scheme != "sim"]
    simulated = [b.simulated for b in BACKENDS if b.scheme == "sim"]
    assert len(real) == len(set(real)) and len(simulated) == len(set(simulated))
    with pytest.raises(ConfigError, match="available: " + ", ".join(f"{s}://" for s in SCHEMES)):
        create_device("x", "usb3vision://cam0", None)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="simulated: " + ", ".join(simulated)):
        create_device("x", "sim://robot", None)  # type: ignore[arg-type]


def test_a_rig_file_kind_is_one_of_the_backends_kinds() -> None:
    devices = {"arm": {"url": "sim://emht", "kind": "robotarm"}}
    with pytest.raises(ConfigError, match=f"unknown kind 'robotarm' \\(kinds: {', '.join(KINDS)}\\)"):
        parse_rig({"rig": {"name": "r", "platform": "p"}, "devices": devices}, "rig.toml")
    devices["arm"]["kind"] = "raven"
    assert parse_rig({"rig": {"name": "r", "platform": "p"}, "devices": devices}, "rig.toml").devices["arm"].kind == "raven"


# --- export formats ---

def test_format_help_lists_exactly_the_registry_and_the_command_help_names_every_target() -> None:
    assert _names_in(_option_help(("export",), "--format")) == list(FORMATS)
    command_help = " ".join(ROOT.commands["export"].help.split())
    for entry in EXPORT_FORMATS:
        assert entry.target in command_help, f"midas export's help does not say what {entry.name} writes"


def test_formats_are_parsed_in_registry_order_and_others_refused() -> None:
    assert parse_formats(["XDF,mcap", "lerobot"]) == [f for f in FORMATS if f in ("xdf", "mcap", "lerobot")]
    with pytest.raises(ConfigError, match="expected one or more of " + ", ".join(FORMATS)):
        parse_formats(["csv"])


# --- reading a table imports nothing it names ---

_PROBE = """import json, sys
import midas_cli.commands.train, midas_cli.commands.export, midas_cli.devices.rigconfig
from midas_cli.devices.registry import create_device, describe_device
before = set(sys.modules)
describe_device("emht", "sim://emht")
print(json.dumps({"before": sorted(before), "after": sorted(set(sys.modules) - before)}))
"""


def test_reading_the_registries_imports_no_backend_writer_or_network() -> None:
    result = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert result.returncode == 0, result.stderr
    loaded = json.loads(result.stdout)
    named = {b.module for b in BACKENDS} | {"midas_cli.models.mstcn", "midas_cli.models.transformer",
                                           "midas_cli.models.baseline", "midas_cli.interop.mcap_export",
                                           "midas_cli.interop.parquet_export", "midas_cli.interop.xdf",
                                           "midas_cli.interop.lerobot_export", "torch"}
    assert not named & set(loaded["before"]), sorted(named & set(loaded["before"]))
    # a URL imports its own backend's module, and no other backend's
    assert "midas_cli.devices.sim.devices" in loaded["after"]
    assert not (named - {"midas_cli.devices.sim.devices"}) & set(loaded["after"])
