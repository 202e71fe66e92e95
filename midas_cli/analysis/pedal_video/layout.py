"""Pedal layouts: where on the console video each pedal shows, and how to read it (TOML data).

A layout file has three parts (see ``midas_cli/data/layouts/davinci-xi.toml``):

* ``[layout]``: ``name``, ``description``, ``reference_size = [width, height]`` of the view the
  coordinates were measured on, and the ``view`` they refer to ("left" eye of a side-by-side stereo
  recording, or "full" frame). Coordinates are stored relative to that size, so a recording at another
  resolution is read at the same relative places, and templates are scaled by the same factor
  (``reference_size = [1, 1]`` takes fractions directly; templates are then used at their stored size).
* ``[regions.<name>]``: ``rect = [x, y, width, height]`` (top-left corner, reference units) and a
  ``detector`` with its settings (see ``detectors.py``).
* ``[pedals.<name>]``: ``regions = [...]`` and a ``rule`` combining their states: "any" (default),
  "all", or "swap" (pressed for ``hold_frames`` frames when exactly ``count`` regions change state in
  the same frame). Pedal names should be the rig's FPS pedal names (``sessions_template/rigs``).
"""

from __future__ import annotations

import hashlib
import tomllib
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path
from typing import Any

from midas_cli.errors import ConfigError

VIEWS = ("left", "full")
RULES = ("any", "all", "swap")
DETECTOR_KINDS = ("color", "hsv", "template", "baseline")
_REGION_COMMON = {"rect", "detector", "description"}
_DETECTOR_KEYS = {
    "color": {"channels", "above", "below"},
    "hsv": {"hue", "sat", "val"},
    "template": {"template", "threshold"},
    "baseline": {"metric", "threshold", "hysteresis", "baseline_frames"},
}
_PEDAL_KEYS = {"regions", "rule", "count", "hold_frames", "description"}


@dataclass(frozen=True)
class RegionSpec:
    """One region of interest: ``rect`` (x, y, w, h) as fractions of the view, its detector settings."""

    name: str
    rect: tuple[float, float, float, float]
    detector: str
    settings: dict[str, Any]

    def pixel_rect(self, width: int, height: int) -> tuple[int, int, int, int]:
        """(x, y, w, h) in pixels of a ``width`` x ``height`` view; at least 1 x 1 pixel."""
        x, y, w, h = self.rect
        return (round(x * width), round(y * height), max(1, round(w * width)), max(1, round(h * height)))


@dataclass(frozen=True)
class PedalRule:
    """How a pedal's state follows from its regions' states (``rule`` is one of RULES)."""

    name: str
    regions: tuple[str, ...]
    rule: str = "any"
    count: int = 2
    hold_frames: int = 15


@dataclass(frozen=True)
class Layout:
    """A parsed layout; ``folder`` is where relative template paths are resolved."""

    name: str
    description: str
    reference_size: tuple[float, float]
    view: str
    regions: dict[str, RegionSpec]
    pedals: dict[str, PedalRule]
    folder: Path
    source: str
    sha256: str = ""

    @property
    def pedal_names(self) -> list[str]:
        return list(self.pedals)

    def describe(self) -> dict[str, Any]:
        """What a result file records about the layout it came from."""
        return {"name": self.name, "source": self.source, "sha256": self.sha256, "view": self.view,
                "reference_size": list(self.reference_size)}


def builtin_layouts() -> list[str]:
    """Names of the layouts shipped in ``midas_cli/data/layouts``."""
    folder = resources.files("midas_cli") / "data" / "layouts"
    return sorted(p.name[: -len(".toml")] for p in folder.iterdir() if p.name.endswith(".toml"))


def load_layout(name_or_path: str | Path) -> Layout:
    """A built-in layout by name (e.g. "davinci-xi") or a layout TOML file by path."""
    path = Path(name_or_path)
    if not path.is_file():
        if str(name_or_path) not in builtin_layouts():
            raise ConfigError(f"layout {str(name_or_path)!r} is neither a file nor a built-in layout "
                              f"(built-in: {', '.join(builtin_layouts())})")
        path = Path(str(resources.files("midas_cli") / "data" / "layouts" / f"{name_or_path}.toml"))
    try:
        raw = path.read_bytes()
        data = tomllib.loads(raw.decode("utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read layout {path}: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"layout {path} is not valid TOML: {exc}") from exc
    return replace(parse_layout(data, path.parent, str(path)), sha256=hashlib.sha256(raw).hexdigest())


def parse_layout(data: dict[str, Any], folder: Path, source: str) -> Layout:
    """Validate a layout dict strictly: unknown keys, bad values and dangling names are errors."""
    _only(data, {"layout", "regions", "pedals"}, source, "")
    head = _table(data, "layout", source)
    _only(head, {"name", "description", "reference_size", "view"}, source, "layout.")
    size = _numbers(head.get("reference_size"), 2, source, "layout.reference_size")
    view = head.get("view", "full")
    if view not in VIEWS or not isinstance(head.get("name"), str) or min(size) <= 0:
        raise ConfigError(f"{source}: layout.name must be a string, layout.view one of {', '.join(VIEWS)} "
                          f"and layout.reference_size positive")
    regions = {n: _region(n, e, size, source) for n, e in _table(data, "regions", source).items()}
    pedals = {n: _pedal(n, e, regions, source) for n, e in _table(data, "pedals", source).items()}
    if not pedals:
        raise ConfigError(f"{source}: no [pedals.<name>] tables")
    return Layout(head["name"], str(head.get("description", "")), (size[0], size[1]), view, regions, pedals,
                  Path(folder), source)


def _region(name: str, entry: Any, size: list[float], source: str) -> RegionSpec:
    if not isinstance(entry, dict):
        raise ConfigError(f"{source}: regions.{name} must be a table")
    kind = entry.get("detector")
    if kind not in DETECTOR_KINDS:
        raise ConfigError(f"{source}: regions.{name}.detector is {kind!r}; expected one of "
                          f"{', '.join(DETECTOR_KINDS)}")
    _only(entry, _REGION_COMMON | _DETECTOR_KEYS[kind], source, f"regions.{name}.")
    x, y, w, h = _numbers(entry.get("rect"), 4, source, f"regions.{name}.rect")
    if w <= 0 or h <= 0 or x < 0 or y < 0 or x + w > size[0] or y + h > size[1]:
        raise ConfigError(f"{source}: regions.{name}.rect {entry['rect']} is not inside the "
                          f"{size[0]:g} x {size[1]:g} reference view")
    rel = (x / size[0], y / size[1], w / size[0], h / size[1])
    settings = {k: v for k, v in entry.items() if k not in _REGION_COMMON}
    return RegionSpec(name, rel, kind, settings)


def _pedal(name: str, entry: Any, regions: dict[str, RegionSpec], source: str) -> PedalRule:
    if not isinstance(entry, dict):
        raise ConfigError(f"{source}: pedals.{name} must be a table")
    _only(entry, _PEDAL_KEYS, source, f"pedals.{name}.")
    names = entry.get("regions")
    if not isinstance(names, list) or not names or any(n not in regions for n in names):
        raise ConfigError(f"{source}: pedals.{name}.regions must list regions defined under [regions] "
                          f"(got {names!r}; defined: {', '.join(regions)})")
    rule = PedalRule(name, tuple(names), entry.get("rule", "any"), int(entry.get("count", 2)),
                     int(entry.get("hold_frames", 15)))
    if rule.rule not in RULES or rule.count < 1 or rule.hold_frames < 1:
        raise ConfigError(f"{source}: pedals.{name}: rule must be one of {', '.join(RULES)}, "
                          f"count and hold_frames >= 1")
    return rule


def _table(data: dict[str, Any], key: str, source: str) -> dict[str, Any]:
    value = data.get(key)
    if not isinstance(value, dict):
        raise ConfigError(f"{source}: missing [{key}] table")
    return value


def _numbers(value: Any, n: int, source: str, key: str) -> list[float]:
    if (not isinstance(value, list) or len(value) != n
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        raise ConfigError(f"{source}: {key} must be a list of {n} numbers, got {value!r}")
    return [float(v) for v in value]


def _only(table: dict[str, Any], allowed: set[str], source: str, prefix: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ConfigError(f"{source}: unknown key {prefix}{unknown[0]} (allowed: {', '.join(sorted(allowed))})")
