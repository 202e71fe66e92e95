"""Reading the pedal board's settings from a rig file and writing calibrated thresholds back into it.

Thresholds live in the device URL (``fps://PORT?...&press_v=1.2,0.9,…&release_v=…``, one value per
channel), so `midas record --rig` hands them to the driver unchanged and the manifest records them;
the channel -> console pedal mapping is the device's ``pedals`` table. The file is edited as text
(comments and other sections are kept), checked with the rig validator, and replaced atomically.
"""

from __future__ import annotations

import json
import os
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlencode

from midas_cli.devices.base import DeviceUrl
from midas_cli.devices.fps.driver import ALLOWED, DEFAULTS, thresholds_from_params
from midas_cli.devices.pedals import DAVINCI_PEDALS
from midas_cli.devices.pedals import PedalThresholds
from midas_cli.devices.rigconfig import load_rig, parse_rig
from midas_cli.errors import ConfigError


@dataclass(frozen=True)
class FpsTarget:
    """The board to calibrate: its URL, its channel -> pedal mapping, its current thresholds."""

    rig_path: Path
    device: str
    url: str
    pedals: dict[int, str]
    thresholds: PedalThresholds


def load_target(rig_path: Path, device: str, url: str | None) -> FpsTarget:
    """The device ``device`` of the rig file (``url`` overrides its URL). A missing file needs ``url``;
    a missing ``pedals`` table means the paper's da Vinci mapping (channels 1-7)."""
    entry_url, table = None, None
    if rig_path.exists():
        rig = load_rig(rig_path)
        if device in rig.devices:
            entry_url, table = rig.devices[device].url, rig.devices[device].extras.get("pedals")
    chosen = url or entry_url
    if chosen is None:
        raise ConfigError(f"{rig_path} has no [devices.{device}] with a url: give --url fps://PORT")
    params = DeviceUrl.parse(chosen).take(ALLOWED, DEFAULTS)
    thresholds = thresholds_from_params(params, chosen)
    pedals = _pedal_map(table, params["channels"], rig_path, device)
    return FpsTarget(rig_path, device, chosen, pedals, thresholds)


def _pedal_map(table: dict | None, channels: int, rig_path: Path, device: str) -> dict[int, str]:
    if table is None:
        return {c: name for c, name in DAVINCI_PEDALS.items() if c <= channels}
    pedals = {}
    for key, name in table.items():
        if not (key.isdigit() and 1 <= int(key) <= channels and isinstance(name, str) and name):
            raise ConfigError(f"{rig_path}: devices.{device}.pedals: {key} = {name!r} must map a channel 1..{channels} "
                              "to a pedal name")
        pedals[int(key)] = name
    if not pedals:
        raise ConfigError(f"{rig_path}: devices.{device}.pedals is empty: map at least one channel to a pedal")
    return pedals


def url_with_thresholds(url: str, thresholds: PedalThresholds) -> str:
    """``url`` with press_v/release_v replaced by one value per channel."""
    parsed = DeviceUrl.parse(url)
    params = dict(parsed.params)
    params["press_v"] = ",".join(f"{v:.3f}" for v in thresholds.press_v)
    params["release_v"] = ",".join(f"{v:.3f}" for v in thresholds.release_v)
    return f"{parsed.scheme}://{parsed.target}?{urlencode(params, safe=',/:')}"


def write_target(target: FpsTarget, thresholds: PedalThresholds) -> str:
    """Write the calibrated URL and the mapping into the rig file (created if missing); returns the URL."""
    url = url_with_thresholds(target.url, thresholds)
    path = target.rig_path
    text = path.read_text(encoding="utf-8") if path.exists() else _new_rig(path)
    updated = _set_device_lines(text, target.device, url, target.pedals)
    rig = parse_rig(_toml(updated, path), str(path))
    written = rig.devices.get(target.device)
    if written is None or written.url != url or written.extras.get("pedals") != {str(k): v for k, v in target.pedals.items()}:
        raise ConfigError(f"could not update [devices.{target.device}] in {path} (unusual layout?): set url = "
                          f"{json.dumps(url)} by hand")
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(updated, encoding="utf-8")
    os.replace(tmp, path)
    return url


def _new_rig(path: Path) -> str:
    return (f"# Rig configuration created by `midas calibrate fps`; add the other devices here.\n\n"
            f"[rig]\nname = {json.dumps(path.stem)}\nplatform = \"unknown\"\n")


def _toml(text: str, path: Path) -> dict:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: editing produced invalid TOML ({exc}); the file was not changed") from exc


def _set_device_lines(text: str, device: str, url: str, pedals: dict[int, str]) -> str:
    """Replace (or add) the url and pedals lines of [devices.<device>], keeping everything else."""
    url_line = f"url = {json.dumps(url)}\n"
    pedals_line = "pedals = { " + ", ".join(f"{c} = {json.dumps(n)}" for c, n in sorted(pedals.items())) + " }\n"
    lines = text.splitlines(keepends=True)
    header = re.compile(rf"^\s*\[\s*devices\.\"?{re.escape(device)}\"?\s*\]\s*(#.*)?$")
    start = next((i for i, line in enumerate(lines) if header.match(line)), None)
    if start is None:
        tail = "" if text.endswith("\n") or not text else "\n"
        return text + tail + f"\n[devices.{device}]\n" + url_line + pedals_line
    end = next((i for i in range(start + 1, len(lines)) if lines[i].lstrip().startswith("[")), len(lines))
    body = [line for line in lines[start + 1:end] if not re.match(r"^\s*(url|pedals)\s*=", line)]
    return "".join(lines[:start + 1] + [url_line, pedals_line] + body + lines[end:])
