"""Region detectors: each turns the pixels of one region of interest (BGR uint8, shape (h, w, 3)) into
an on/off state and a score, one frame at a time.

* ``color``    -- mean of the chosen BGR channels over the region; on when ``> above`` (or ``< below``).
* ``hsv``      -- the region's mean colour in OpenCV HSV (H 0-179, S and V 0-255); on when inside the
                  ``hue``/``sat``/``val`` ranges (a hue range with lo > hi wraps around red).
* ``template`` -- greyscale template matched with TM_CCOEFF_NORMED; on when the best score >= threshold.
* ``baseline`` -- mean of a channel (b, g, r or v = HSV value) compared with its mean over the first
                  ``baseline_frames`` frames; on when |change| >= threshold, off again when
                  |change| <= threshold - hysteresis (stateful: feed frames in order).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import cv2
import numpy as np

from midas_cli.analysis.pedal_video.layout import Layout, RegionSpec
from midas_cli.errors import ConfigError

_CHANNEL = {"b": 0, "g": 1, "r": 2}


class Detector(Protocol):
    stateful: bool

    def evaluate(self, roi: np.ndarray) -> tuple[bool, float]:
        """(state, score) for one frame's region pixels."""


@dataclass
class ColorThreshold:
    channels: tuple[int, ...]
    above: float | None = None
    below: float | None = None
    stateful: bool = False

    def evaluate(self, roi: np.ndarray) -> tuple[bool, float]:
        score = float(np.mean([roi[:, :, c].mean() for c in self.channels]))
        return (score > self.above) if self.above is not None else (score < self.below), score


@dataclass
class HsvClass:
    hue: tuple[float, float] = (0, 179)
    sat: tuple[float, float] = (0, 255)
    val: tuple[float, float] = (0, 255)
    stateful: bool = False

    def evaluate(self, roi: np.ndarray) -> tuple[bool, float]:
        mean = np.clip(roi.reshape(-1, 3).mean(axis=0).round(), 0, 255).astype(np.uint8).reshape(1, 1, 3)
        h, s, v = (float(x) for x in cv2.cvtColor(mean, cv2.COLOR_BGR2HSV)[0, 0])
        lo, hi = self.hue
        hue_ok = lo <= h <= hi if lo <= hi else (h >= lo or h <= hi)
        return hue_ok and self.sat[0] <= s <= self.sat[1] and self.val[0] <= v <= self.val[1], h


@dataclass
class TemplateMatch:
    """``templates``: (th, tw) uint8 greyscale versions of one icon, scaled to the frame (one per
    sub-pixel phase when the frame is smaller than the reference); the best score over all counts."""

    templates: list[np.ndarray]
    threshold: float = 0.80
    stateful: bool = False

    def evaluate(self, roi: np.ndarray) -> tuple[bool, float]:
        gray = cv2.cvtColor(roi, cv2.COLOR_BGR2GRAY)
        score = max(float(cv2.matchTemplate(gray, t, cv2.TM_CCOEFF_NORMED).max()) for t in self.templates)
        return score >= self.threshold, score


@dataclass
class BaselineChange:
    metric: str = "v"
    threshold: float = 20.0
    hysteresis: float = 5.0
    baseline_frames: int = 30
    stateful: bool = True
    _seen: list[float] = field(default_factory=list)
    _on: bool = False

    def evaluate(self, roi: np.ndarray) -> tuple[bool, float]:
        value = float(roi.max(axis=2).mean() if self.metric == "v" else roi[:, :, _CHANNEL[self.metric]].mean())
        if len(self._seen) < self.baseline_frames:
            self._seen.append(value)
        change = abs(value - float(np.mean(self._seen)))
        if not self._on and change >= self.threshold:
            self._on = True
        elif self._on and change <= self.threshold - self.hysteresis:
            self._on = False
        return self._on, change


def build_detector(region: RegionSpec, layout: Layout, view_size: tuple[int, int]) -> Detector:
    """A fresh detector for ``region`` on a view of ``view_size`` = (width, height) pixels."""
    s, where = region.settings, f"{layout.source}: regions.{region.name}"
    if region.detector == "color":
        return _color(s, where)
    if region.detector == "hsv":
        ranges = {k: _range(s.get(k, default), where, k) for k, default in
                  (("hue", [0, 179]), ("sat", [0, 255]), ("val", [0, 255]))}
        return HsvClass(**ranges)
    if region.detector == "template":
        return TemplateMatch(_scaled_templates(region, layout, view_size), float(s.get("threshold", 0.80)))
    metric = s.get("metric", "v")
    if metric not in ("b", "g", "r", "v"):
        raise ConfigError(f"{where}.metric is {metric!r}; expected b, g, r or v")
    detector = BaselineChange(metric, float(s.get("threshold", 20.0)), float(s.get("hysteresis", 5.0)),
                              int(s.get("baseline_frames", 30)))
    if detector.baseline_frames < 1 or not 0 <= detector.hysteresis <= detector.threshold:
        raise ConfigError(f"{where}: need baseline_frames >= 1 and 0 <= hysteresis <= threshold")
    return detector


def _color(s: dict[str, Any], where: str) -> ColorThreshold:
    channels = s.get("channels", "")
    if not isinstance(channels, str) or not channels or any(c not in _CHANNEL for c in channels):
        raise ConfigError(f"{where}.channels is {channels!r}; expected letters from 'bgr', e.g. \"gr\"")
    if ("above" in s) == ("below" in s):
        raise ConfigError(f"{where}: a color detector needs exactly one of above = N or below = N")
    above, below = s.get("above"), s.get("below")
    return ColorThreshold(tuple(_CHANNEL[c] for c in channels), None if above is None else float(above),
                          None if below is None else float(below))


def _range(value: Any, where: str, key: str) -> tuple[float, float]:
    if not isinstance(value, list) or len(value) != 2 or not all(isinstance(v, (int, float)) for v in value):
        raise ConfigError(f"{where}.{key} must be [low, high], got {value!r}")
    return float(value[0]), float(value[1])


def load_template(region: RegionSpec, layout: Layout) -> np.ndarray:
    """The region's template as stored (greyscale uint8), from a PNG path relative to the layout file."""
    rel = region.settings.get("template")
    path = layout.folder / str(rel)
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if isinstance(rel, str) and path.is_file() else None
    if image is None:
        raise ConfigError(f"{layout.source}: regions.{region.name}.template {rel!r} is not a readable image "
                          f"(looked for {path})")
    return image


def _scaled_templates(region: RegionSpec, layout: Layout, view_size: tuple[int, int]) -> list[np.ndarray]:
    """The template at the view's scale. Shrunk icons of a few pixels depend on where the pixel grid
    falls, so a shrunk template is made at 3 x 3 sub-pixel phases (shifted by thirds of a view pixel)."""
    template = load_template(region, layout)
    sx, sy = view_size[0] / layout.reference_size[0], view_size[1] / layout.reference_size[1]
    if layout.reference_size == (1.0, 1.0) or (sx == 1 and sy == 1):
        templates = [template]
    else:
        size = (max(1, round(template.shape[1] * sx)), max(1, round(template.shape[0] * sy)))
        phases = [(px / sx, py / sy) for px in (0, 1 / 3, 2 / 3) for py in (0, 1 / 3, 2 / 3)] if min(sx, sy) < 1 \
            else [(0.0, 0.0)]
        templates = [_resample(template, size, dx, dy, sx < 1) for dx, dy in phases]
    _, _, w, h = region.pixel_rect(*view_size)
    if templates[0].shape[0] > h or templates[0].shape[1] > w:
        raise ConfigError(f"{layout.source}: regions.{region.name}: template {templates[0].shape[1]}x"
                          f"{templates[0].shape[0]} px is larger than the region ({w}x{h} px at this resolution)")
    return templates


def _resample(template: np.ndarray, size: tuple[int, int], dx: float, dy: float, shrink: bool) -> np.ndarray:
    """``template`` moved by (dx, dy) reference pixels (edges repeated), then resized to ``size``."""
    if dx or dy:
        template = cv2.warpAffine(template, np.float32([[1, 0, dx], [0, 1, dy]]), template.shape[::-1],
                                  flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return cv2.resize(template, size, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
