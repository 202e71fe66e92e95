"""Rig configuration files (TOML): which devices a console has, and session metadata defaults.

Keys are validated strictly: an unknown key is an error naming the key and the file, never ignored.
Templates live in ``sessions_template/rigs/``. A rig file holds no secret (it is shared, copied and
stored in every session's manifest): a ``password`` key (or any key that names a secret) is refused
with a line saying where the password goes (``password_env``, the name of an environment variable, or
``password_file``, a file only its owner may read; a relative one is relative to the rig file).

Here, below the rig layer, because device code edits rig files too (``devices/fps/rigfile.py`` writes
calibrated pedal thresholds back and validates the result); ``midas_cli/rig.py`` builds on this.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote

from midas_cli.config import read_toml
from midas_cli.devices.base import WHERE_PASSWORDS_GO, DeviceUrl, is_secret_key
from midas_cli.devices.registry import KINDS
from midas_cli.errors import ConfigError
from midas_cli.session.names import check_name

RIG_KEYS = {"name": str, "platform": str, "master_rate_hz": (int, float), "description": str}
METADATA_KEYS = {"subject": (str, int), "task": str, "trial": int, "operator_note": str}
DEVICE_KEYS = {"url": str, "kind": str, "description": str, "sensors": dict, "pedals": dict,
               "password_env": str, "password_file": str}
LIVE_KEYS = {"model": str}  # [live] model = "RUN": `record --live-model RUN` (relative to the rig file)
PASSWORD_SOURCES = ("password_env", "password_file")  # where a password is: they travel as URL parameters


@dataclass
class DeviceConfig:
    name: str
    url: str
    kind: str
    extras: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_device_name(self.name)


def check_device_name(name: str) -> None:
    """A device name names its stream files: a letter, then up to 31 letters, digits, '_' or '-'."""
    check_name(name, "device", "device name", ConfigError)


@dataclass
class RigConfig:
    name: str
    platform: str
    master_rate_hz: float = 30.0
    description: str = ""
    metadata: dict[str, Any] = field(default_factory=dict)
    devices: dict[str, DeviceConfig] = field(default_factory=dict)
    source: str = ""
    live_model: str | None = None  # [live] model: the run recognised live by `midas record` (an absolute path)

    def device_urls(self) -> dict[str, str]:
        """Device name -> URL; ``password_env`` and ``password_file`` keys travel as URL parameters (the
        name of an environment variable or a file, never a password), so the backend reads the password
        in its worker."""
        return {name: _with_password_source(device) for name, device in self.devices.items()}

    def to_manifest(self) -> dict[str, Any]:
        """The rig as recorded in a manifest (URLs shown redacted, though a URL holding credentials
        never gets this far: ``DeviceUrl.parse`` refuses it)."""
        devices = {}
        for name, device in self.devices.items():
            devices[name] = {"url": DeviceUrl.parse(device.url).redacted(), "kind": device.kind, **device.extras}
        return {"name": self.name, "platform": self.platform, "master_rate_hz": self.master_rate_hz,
                "description": self.description, "source": self.source, "devices": devices}


def _with_password_source(device: DeviceConfig) -> str:
    sources = "&".join(f"{key}={quote(device.extras[key])}" for key in PASSWORD_SOURCES if device.extras.get(key))
    if not sources:
        return device.url
    return device.url + ("&" if "?" in device.url else "?") + sources


def load_rig(path: Path | str) -> RigConfig:
    """The rig file at ``path``, checked; ConfigError for a missing, special (/dev/zero), huge, non-UTF-8,
    invalid or too deeply nested file (``config.read_toml``) and for any bad section, key or value."""
    path = Path(path)
    try:
        data = read_toml(path, "rig file")
    except FileNotFoundError:
        raise ConfigError(f"rig file {path} does not exist") from None
    return parse_rig(data, str(path))


def parse_rig(data: dict[str, Any], source: str) -> RigConfig:
    _check_keys(data, {"rig": dict, "metadata": dict, "devices": dict, "live": dict}, source, "")
    rig = data.get("rig")
    if rig is None:
        raise ConfigError(f"{source}: missing [rig] section")
    _check_keys(rig, RIG_KEYS, source, "rig.")
    for key in ("name", "platform"):
        if key not in rig:
            raise ConfigError(f"{source}: missing rig.{key}")
    metadata = data.get("metadata", {})
    _check_keys(metadata, METADATA_KEYS, source, "metadata.")
    devices = {name: _parse_device(name, entry, source) for name, entry in data.get("devices", {}).items()}
    if not devices:
        raise ConfigError(f"{source}: no [devices.<name>] sections")
    live = data.get("live", {})
    _check_keys(live, LIVE_KEYS, source, "live.")
    model = str(Path(source).parent / Path(live["model"]).expanduser()) if "model" in live else None
    return RigConfig(rig["name"], rig["platform"], float(rig.get("master_rate_hz", 30.0)),
                     rig.get("description", ""), metadata, devices, source, model)


def _parse_device(name: str, entry: Any, source: str) -> DeviceConfig:
    if not isinstance(entry, dict):
        raise ConfigError(f"{source}: devices.{name} must be a table")
    _refuse_secrets(entry, source, f"devices.{name}.")
    _check_keys(entry, DEVICE_KEYS, source, f"devices.{name}.")
    if "url" not in entry:
        raise ConfigError(f"{source}: devices.{name} has no url")
    kind = entry.get("kind", name)
    if kind not in KINDS:
        raise ConfigError(f"{source}: devices.{name}: unknown kind {kind!r} (kinds: {', '.join(KINDS)})")
    try:
        DeviceUrl.parse(entry["url"])
    except ConfigError as exc:
        raise ConfigError(f"{source}: devices.{name}.url: {exc}") from None
    extras = {k: v for k, v in entry.items() if k not in ("url", "kind")}
    if extras.get("password_file"):  # relative to the rig file, wherever midas runs
        extras["password_file"] = str(Path(source).parent / Path(extras["password_file"]).expanduser())
    return DeviceConfig(name, entry["url"], kind, extras)


def _refuse_secrets(table: dict[str, Any], source: str, prefix: str) -> None:
    """A secret in a rig file is refused, never ignored: the line names the key (not its value) and
    where the password goes instead."""
    for key in table:
        if is_secret_key(key):
            raise ConfigError(f"{source}: {prefix}{key}: a rig file holds no passwords (it is shared, copied and "
                              f"stored in every session's manifest); remove it and {WHERE_PASSWORDS_GO}")


def _check_keys(table: dict[str, Any], allowed: dict[str, Any], source: str, prefix: str) -> None:
    for key, value in table.items():
        if key not in allowed:
            raise ConfigError(f"{source}: unknown key {prefix}{key} (allowed: {', '.join(allowed)})")
        if not isinstance(value, allowed[key]) or isinstance(value, bool):
            raise ConfigError(f"{source}: {prefix}{key} has the wrong type ({type(value).__name__})")
