"""Gesture taxonomies as data: ``midas_cli/data/taxonomies/<name>.toml``, loaded and validated here.

A taxonomy file has ``name``, ``title``, ``source``, optionally ``idle`` (the id of the class that
fills unannotated time when asked to), and a list ``[[gestures]]`` with ``id``, ``name`` and optional
``description``, ``goal``, ``main_arm``, ``support_arm``. Gesture ids are the label strings stored in
frame-label sets (``G1``, ``S3``, ``Idle``).
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from midas_cli.errors import ConfigError

_ID_OK = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_TOP_KEYS = {"name", "title", "source", "idle", "gestures"}
_GESTURE_KEYS = {"id", "name", "description", "goal", "main_arm", "support_arm"}


@dataclass(frozen=True)
class Gesture:
    """One class of a taxonomy; ``id`` is the stored label."""

    id: str
    name: str
    description: str = ""
    goal: str = ""
    main_arm: str = ""
    support_arm: str = ""

    def to_json(self) -> dict[str, str]:
        return {k: v for k, v in self.__dict__.items() if v}


@dataclass(frozen=True)
class Taxonomy:
    """An ordered set of gestures; order is the display order of tables and matrices."""

    name: str
    title: str
    source: str
    gestures: tuple[Gesture, ...]
    idle: str | None = None

    @property
    def ids(self) -> list[str]:
        return [g.id for g in self.gestures]

    def gesture(self, gesture_id: str) -> Gesture:
        for g in self.gestures:
            if g.id == gesture_id:
                return g
        raise ConfigError(f"gesture {gesture_id!r} is not in taxonomy {self.name!r} (ids: {', '.join(self.ids)})")

    def resolve(self, text: str) -> str | None:
        """The gesture id that ``text`` names: an id or a name (any case), or ``"<id> <name>"`` style
        text such as ``"G1 Orient Needle"`` / ``"G1: Orient Needle"``; None when nothing matches."""
        wanted = text.strip().casefold()
        for g in self.gestures:
            if wanted in (g.id.casefold(), g.name.casefold()):
                return g.id
        for g in sorted(self.gestures, key=lambda g: -len(g.id)):
            if re.match(re.escape(g.id.casefold()) + r"[\s:._-]", wanted):
                return g.id
        return None

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "title": self.title, "source": self.source, "idle": self.idle,
                "gestures": [g.to_json() for g in self.gestures]}


def taxonomy_folder() -> Path:
    return Path(str(resources.files("midas_cli") / "data" / "taxonomies"))


def list_taxonomies() -> list[str]:
    """Names of the taxonomies shipped with the package."""
    return sorted(p.stem for p in taxonomy_folder().glob("*.toml"))


def load_taxonomy(name_or_path: str) -> Taxonomy:
    """A shipped taxonomy by name (``hernia-suturing``) or any ``.toml`` file by path."""
    path = Path(name_or_path)
    if path.suffix != ".toml":
        path = taxonomy_folder() / f"{name_or_path}.toml"
        if not path.is_file():
            raise ConfigError(f"unknown taxonomy {name_or_path!r}; shipped: {', '.join(list_taxonomies())} "
                              "(or give the path of a .toml file)")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"cannot read taxonomy {path}: {exc}") from exc
    return parse_taxonomy(data, str(path))


def shipped_taxonomy(name: str) -> Taxonomy:
    """A taxonomy shipped with midas, by name only: for the names label sets record, which come from the
    session and are never read as a path (ConfigError for any other name)."""
    if name not in list_taxonomies():
        raise ConfigError(f"unknown taxonomy {name!r}; shipped: {', '.join(list_taxonomies())}")
    return load_taxonomy(name)


def parse_taxonomy(data: dict[str, Any], where: str) -> Taxonomy:
    """Validate a taxonomy mapping (as read from TOML); ``where`` names it in error messages."""
    unknown = set(data) - _TOP_KEYS
    if unknown or not data.get("name") or not isinstance(data.get("gestures"), list) or not data["gestures"]:
        raise ConfigError(f"taxonomy {where}: expected keys name, title, source, [idle], [[gestures]]; "
                          f"got {sorted(data)}")
    gestures = tuple(_parse_gesture(entry, where) for entry in data["gestures"])
    ids = [g.id for g in gestures]
    duplicates = sorted({i for i in ids if ids.count(i) > 1})
    if duplicates:
        raise ConfigError(f"taxonomy {where}: duplicate gesture id(s) {', '.join(duplicates)}")
    idle = data.get("idle")
    if idle is not None and idle not in ids:
        raise ConfigError(f"taxonomy {where}: idle class {idle!r} is not one of its gesture ids")
    return Taxonomy(str(data["name"]), str(data.get("title", "")), str(data.get("source", "")), gestures, idle)


def _parse_gesture(entry: Any, where: str) -> Gesture:
    if not isinstance(entry, dict) or set(entry) - _GESTURE_KEYS or "id" not in entry or "name" not in entry:
        raise ConfigError(f"taxonomy {where}: each gesture needs id and name (optional: description, goal, "
                          f"main_arm, support_arm); got {entry!r}")
    if not _ID_OK.match(str(entry["id"])):
        raise ConfigError(f"taxonomy {where}: gesture id {entry['id']!r} must be letters, digits, '_', '.' or '-'")
    return Gesture(**{k: str(v) for k, v in entry.items()})
