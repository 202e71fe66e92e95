"""Dataset statistics of gesture segments: the layout of the paper's dataset table, and transitions.

Per gesture: number of segments ("samples") and mean ± sample standard deviation (ddof=1) of segment
duration in seconds, ``frames / fps`` with inclusive frame ranges. Totals: classes, samples, minutes
and minutes per recording. Transitions count consecutive segments of one recording (an unlabelled gap
between them does not break the transition).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from midas_cli.errors import ConfigError
from midas_cli.labels.segments import FrameSegment
from midas_cli.labels.taxonomy import Taxonomy
from midas_cli.session.outputs import out_target, write_bytes


@dataclass(frozen=True)
class Recording:
    """The segments of one session or transcription file, in time order; ``fps`` in Hz."""

    name: str
    segments: tuple[FrameSegment, ...]
    fps: float


@dataclass
class GestureStats:
    classes: list[str]
    names: dict[str, str]
    samples: dict[str, int]
    mean_s: dict[str, float]
    std_s: dict[str, float | None]
    total_s: float
    recordings: int
    transitions: np.ndarray  # (C, C) int: transitions[i, j] = count of class i followed by class j

    def to_json(self) -> dict[str, Any]:
        rows = [{"id": c, "name": self.names.get(c, ""), "samples": self.samples[c],
                 "mean_s": round(self.mean_s[c], 4),
                 "std_s": None if self.std_s[c] is None else round(self.std_s[c], 4)} for c in self.classes]
        return {"classes": len(self.classes), "samples": sum(self.samples.values()),
                "total_min": round(self.total_s / 60, 3), "recordings": self.recordings,
                "min_per_recording": round(self.total_s / 60 / max(self.recordings, 1), 3), "gestures": rows,
                "transitions": {"labels": self.classes, "counts": self.transitions.tolist()}}


def natural_key(label: str) -> list[Any]:
    """Sort key that puts G2 before G10."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", label)]


def gesture_stats(recordings: Sequence[Recording], taxonomy: Taxonomy | None = None,
                  exclude: Sequence[str] = ()) -> GestureStats:
    """Counts, durations and the transition matrix over all ``recordings``; segments labelled with one
    of ``exclude`` (e.g. Idle, to match the paper's table) are left out as if absent."""
    recordings = [Recording(r.name, tuple(s for s in r.segments if s.label not in exclude), r.fps)
                  for r in recordings]
    durations: dict[str, list[float]] = {}
    for rec in recordings:
        for seg in rec.segments:
            durations.setdefault(seg.label, []).append(seg.frames / rec.fps)
    classes = _ordered(durations, taxonomy, recordings)
    index = {c: i for i, c in enumerate(classes)}
    transitions = np.zeros((len(classes), len(classes)), dtype=np.int64)
    for rec in recordings:
        for a, b in zip(rec.segments, rec.segments[1:]):
            transitions[index[a.label], index[b.label]] += 1
    names = {g.id: g.name for g in taxonomy.gestures} if taxonomy else {}
    return GestureStats(
        classes, names, {c: len(durations[c]) for c in classes},
        {c: float(np.mean(durations[c])) for c in classes},
        {c: float(np.std(durations[c], ddof=1)) if len(durations[c]) > 1 else None for c in classes},
        float(sum(sum(v) for v in durations.values())), len(recordings), transitions)


def _ordered(durations: dict[str, list[float]], taxonomy: Taxonomy | None,
             recordings: Sequence[Recording]) -> list[str]:
    if taxonomy is None:
        return sorted(durations, key=natural_key)
    unknown = sorted(set(durations) - set(taxonomy.ids), key=natural_key)
    if unknown:
        where = next(r.name for r in recordings if any(s.label == unknown[0] for s in r.segments))
        raise ConfigError(f"label(s) {', '.join(unknown)} (e.g. in {where}) are not in taxonomy {taxonomy.name!r} "
                          f"(ids: {', '.join(taxonomy.ids)})")
    return [g for g in taxonomy.ids if g in durations]


def transition_heatmap(stats: GestureStats, path: Path, cell_px: int = 56,
                       title: str = "Gesture transitions (counts)") -> Path:
    """Write the transition matrix as a PNG heatmap (OpenCV): row = from, column = to, counts in cells,
    with a title, axis labels and a colour bar (viridis, 0 to the largest count)."""
    import cv2

    n = len(stats.classes)
    top, left, bar_w = cell_px + 60, cell_px + 30, 18
    image = np.full((top + n * cell_px + 20, max(left + n * cell_px + 40 + bar_w + 50, 420), 3), 255, dtype=np.uint8)
    peak = max(int(stats.transitions.max()), 1) if n else 1
    scaled = (255 * stats.transitions / peak).astype(np.uint8)
    colours = cv2.applyColorMap(scaled.reshape(n, n, 1) if n else np.zeros((1, 1, 1), np.uint8), cv2.COLORMAP_VIRIDIS)
    font, scale, ink_black = cv2.FONT_HERSHEY_SIMPLEX, cell_px / 140, (0, 0, 0)
    cv2.putText(image, title[:60], (10, 24), font, 0.6, ink_black, 1, cv2.LINE_AA)
    cv2.putText(image, "to (next gesture)", (left, top - 32), font, 0.5, ink_black, 1, cv2.LINE_AA)
    (label_w, label_h), _ = cv2.getTextSize("from", font, 0.5, 1)
    patch = np.full((label_h + 6, label_w + 2, 3), 255, np.uint8)
    cv2.putText(patch, "from", (1, label_h + 1), font, 0.5, ink_black, 1, cv2.LINE_AA)
    patch = cv2.rotate(patch, cv2.ROTATE_90_COUNTERCLOCKWISE)
    y0 = top + max(0, (n * cell_px - patch.shape[0]) // 2)
    image[y0:y0 + patch.shape[0], 4:4 + patch.shape[1]] = patch
    for i, label in enumerate(stats.classes):
        cv2.putText(image, label, (26, top + i * cell_px + cell_px // 2 + 5), font, scale, ink_black, 1, cv2.LINE_AA)
        cv2.putText(image, label, (left + i * cell_px + 6, top - 10), font, scale, ink_black, 1, cv2.LINE_AA)
        for j in range(n):
            x, y = left + j * cell_px, top + i * cell_px
            colour = tuple(int(c) for c in colours[i, j])
            cv2.rectangle(image, (x, y), (x + cell_px - 1, y + cell_px - 1), colour, thickness=-1)
            ink = (0, 0, 0) if scaled[i, j] > 150 else (255, 255, 255)
            cv2.putText(image, str(stats.transitions[i, j]), (x + 6, y + cell_px // 2 + 5), font, scale, ink, 1,
                        cv2.LINE_AA)
    bar_x, bar_h = left + n * cell_px + 40, max(n * cell_px, 60)
    ramp = cv2.applyColorMap(np.linspace(255, 0, bar_h).astype(np.uint8).reshape(bar_h, 1, 1), cv2.COLORMAP_VIRIDIS)
    image[top:top + bar_h, bar_x:bar_x + bar_w] = ramp.reshape(bar_h, 1, 3)
    cv2.putText(image, str(peak), (bar_x + bar_w + 4, top + 10), font, 0.4, ink_black, 1, cv2.LINE_AA)
    cv2.putText(image, "0", (bar_x + bar_w + 4, top + bar_h), font, 0.4, ink_black, 1, cv2.LINE_AA)
    try:
        ok, encoded = cv2.imencode(Path(path).suffix or ".png", image)
    except cv2.error:  # a suffix OpenCV has no encoder for (.csv) raises rather than returning False
        ok = False
    if not ok:
        raise ConfigError(f"cannot write the heatmap to {path}: name it .png")
    return write_bytes(out_target(path, "--plot"), encoded.tobytes())
