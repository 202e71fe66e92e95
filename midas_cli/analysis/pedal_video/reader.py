"""Reading a layout's regions from frames: a layout bound to one view size, evaluated frame by frame.

``FrameReader`` holds fresh detectors (baseline detectors and swap rules keep state, so one reader per
video, fed frames in order) and the pixel rectangles of every region for the view it was built for.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from midas_cli.analysis.pedal_video.detectors import Detector, build_detector
from midas_cli.analysis.pedal_video.layout import Layout, PedalRule
from midas_cli.errors import ConfigError


@dataclass
class FrameReading:
    """One frame: per-region (state, score) and per-pedal state, in layout order."""

    regions: dict[str, tuple[bool, float]]
    pedals: dict[str, bool]


@dataclass
class _SwapState:
    previous: tuple[bool, ...] | None = None
    hold_left: int = 0


@dataclass
class FrameReader:
    layout: Layout
    view_size: tuple[int, int]
    rects: dict[str, tuple[int, int, int, int]] = field(init=False)
    detectors: dict[str, Detector] = field(init=False)
    _swaps: dict[str, _SwapState] = field(init=False)

    def __post_init__(self) -> None:
        width, height = self.view_size
        self.rects = {name: r.pixel_rect(width, height) for name, r in self.layout.regions.items()}
        for name, (x, y, w, h) in self.rects.items():
            if x + w > width or y + h > height:
                raise ConfigError(f"{self.layout.source}: region {name} ({x},{y},{w}x{h} px) falls outside the "
                                  f"{width}x{height} view")
        self.detectors = {name: build_detector(r, self.layout, self.view_size)
                          for name, r in self.layout.regions.items()}
        self._swaps = {name: _SwapState() for name, p in self.layout.pedals.items() if p.rule == "swap"}

    @property
    def stateful(self) -> bool:
        """True when a frame's result depends on earlier frames (baseline detectors, swap rules)."""
        return bool(self._swaps) or any(d.stateful for d in self.detectors.values())

    def read(self, view: np.ndarray) -> FrameReading:
        """Evaluate every region on ``view`` (H, W, 3) BGR uint8 of ``view_size``, then every pedal."""
        if (view.shape[1], view.shape[0]) != self.view_size:
            raise ConfigError(f"frame view is {view.shape[1]}x{view.shape[0]}, reader built for "
                              f"{self.view_size[0]}x{self.view_size[1]}")
        regions = {}
        for name, (x, y, w, h) in self.rects.items():
            regions[name] = self.detectors[name].evaluate(view[y:y + h, x:x + w])
        pedals = {name: self._combine(rule, [regions[r][0] for r in rule.regions])
                  for name, rule in self.layout.pedals.items()}
        return FrameReading(regions, pedals)

    def _combine(self, rule: PedalRule, states: list[bool]) -> bool:
        if rule.rule == "any":
            return any(states)
        if rule.rule == "all":
            return all(states)
        swap = self._swaps[rule.name]
        current = tuple(states)
        if swap.previous is not None and sum(a != b for a, b in zip(swap.previous, current)) == rule.count:
            swap.hold_left = rule.hold_frames
        swap.previous = current
        pressed = swap.hold_left > 0
        swap.hold_left = max(0, swap.hold_left - 1)
        return pressed
