"""Result figures drawn with OpenCV (no matplotlib dependency): confusion matrix, prediction ribbons."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from midas_cli.errors import SessionError
from midas_cli.session.outputs import out_target, replacing

FONT = cv2.FONT_HERSHEY_SIMPLEX
WHITE, BLACK, GREY = (255, 255, 255), (0, 0, 0), (200, 200, 200)


def class_colours(n: int) -> list[tuple[int, int, int]]:
    """n distinct BGR colours (hues spread evenly, full saturation)."""
    hues = np.linspace(0, 180, n, endpoint=False).astype(np.uint8)
    hsv = np.stack([hues, np.full(n, 200, np.uint8), np.full(n, 230, np.uint8)], axis=1)[None]  # (1, n, 3)
    return [tuple(int(c) for c in bgr) for bgr in cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0]]


def write_confusion_png(path: Path, matrix: np.ndarray, classes: Sequence[str], cell: int = 56,
                        title: str = "Confusion matrix (test frames)") -> Path:
    """Row-normalised confusion matrix (rows = truth, columns = prediction) with counts, as a PNG: a
    title, axis labels and a colour bar (share of the row's frames, 0-100 %)."""
    n = len(classes)
    top, left, bar_w = 90, 110, 18
    width = left + n * cell + 30 + bar_w + 60
    image = np.full((top + n * cell + 50, max(width, 420), 3), 255, np.uint8)
    rows = matrix.sum(axis=1, keepdims=True)
    share = np.divide(matrix, rows, out=np.zeros(matrix.shape, float), where=rows > 0)
    cv2.putText(image, title[:60], (10, 24), FONT, 0.6, BLACK, 1, cv2.LINE_AA)
    cv2.putText(image, "predicted", (left + n * cell // 2 - 35, 48), FONT, 0.5, BLACK, 1, cv2.LINE_AA)
    for i in range(n):
        for j in range(n):
            top_left = (left + j * cell, top + i * cell)
            cv2.rectangle(image, top_left, (top_left[0] + cell - 1, top_left[1] + cell - 1), _blue(share[i, j]), -1)
            colour = WHITE if share[i, j] > 0.5 else BLACK
            cv2.putText(image, str(int(matrix[i, j])), (top_left[0] + 4, top_left[1] + cell // 2 + 5), FONT, 0.4, colour, 1)
        cv2.putText(image, classes[i][:10], (28, top + i * cell + cell // 2 + 5), FONT, 0.45, BLACK, 1)
        cv2.putText(image, classes[i][:7], (left + i * cell + 2, top - 8), FONT, 0.45, BLACK, 1)
    _vertical_text(image, "truth", (6, top + n * cell // 2 + 20))
    cv2.putText(image, "counts; shade = share of the truth row", (left, top + n * cell + 25), FONT, 0.45, BLACK, 1)
    _colour_bar(image, (left + n * cell + 30, top), bar_w, max(n * cell, 60), _blue, "0%", "100%")
    return _save(path, image)


def _blue(value: float) -> tuple[int, int, int]:
    """White (0) to blue (1), BGR."""
    shade = int(255 * (1 - float(np.clip(value, 0, 1))))
    return 255, shade, shade


def _colour_bar(image: np.ndarray, origin: tuple[int, int], width: int, height: int, colour_of,
                low: str, high: str) -> None:
    """A vertical colour bar (``colour_of(0..1)``, high at the top) with its end values written beside it."""
    x, y = origin
    for k in range(height):
        cv2.line(image, (x, y + k), (x + width, y + k), colour_of(1 - k / max(1, height - 1)), 1)
    cv2.rectangle(image, (x, y), (x + width, y + height), BLACK, 1)
    cv2.putText(image, high, (x + width + 4, y + 10), FONT, 0.4, BLACK, 1)
    cv2.putText(image, low, (x + width + 4, y + height), FONT, 0.4, BLACK, 1)


def _vertical_text(image: np.ndarray, text: str, bottom_left: tuple[int, int]) -> None:
    """``text`` written bottom to top with its baseline's start at ``bottom_left``."""
    (w, h), _ = cv2.getTextSize(text, FONT, 0.5, 1)
    patch = np.full((h + 6, w + 2, 3), 255, np.uint8)
    cv2.putText(patch, text, (1, h + 1), FONT, 0.5, BLACK, 1, cv2.LINE_AA)
    rotated = cv2.rotate(patch, cv2.ROTATE_90_COUNTERCLOCKWISE)
    x, y = bottom_left
    y0 = max(0, y - rotated.shape[0])
    image[y0:y0 + rotated.shape[0], x:x + rotated.shape[1]] = rotated[: image.shape[0] - y0, : image.shape[1] - x]


def write_timeline_png(path: Path, truth: np.ndarray, prediction: np.ndarray, classes: Sequence[str],
                       title: str, width: int = 1000) -> Path:
    """Two colour ribbons over time: ground truth (top) and prediction (bottom, grey = not tested)."""
    colours = class_colours(len(classes))
    band, top = 40, 30
    legend_rows = (len(classes) + 6) // 6  # + the grey entry
    image = np.full((top + 2 * band + 30 + 22 * legend_rows, width + 110, 3), 255, np.uint8)
    cv2.putText(image, title[:90], (5, 20), FONT, 0.5, BLACK, 1)
    for row, (name, labels) in enumerate((("truth", truth), ("predicted", prediction))):
        y0 = top + row * (band + 10)
        cv2.putText(image, name, (5, y0 + band // 2 + 5), FONT, 0.45, BLACK, 1)
        columns = (np.arange(width) * len(labels) // width) if len(labels) else np.zeros(0, int)
        for x, idx in enumerate(columns):
            label = labels[idx]
            cv2.line(image, (100 + x, y0), (100 + x, y0 + band), colours[label] if label >= 0 else GREY, 1)
    for k, (name, colour) in enumerate([*zip(classes, colours), ("grey = not tested", GREY)]):
        x0, y0 = 100 + (k % 6) * 150, top + 2 * band + 30 + (k // 6) * 22
        cv2.rectangle(image, (x0, y0 - 12), (x0 + 14, y0 + 2), colour, -1)
        cv2.putText(image, name[:17], (x0 + 20, y0), FONT, 0.45 if k < len(classes) else 0.4, BLACK, 1)
    return _save(path, image)


def _save(path: Path, image: np.ndarray) -> Path:
    path = Path(path)
    ok, encoded = cv2.imencode(path.suffix or ".png", image)
    if not ok:
        raise SessionError(f"cannot write {path}: no image format for {path.suffix!r}")
    with replacing(out_target(path)) as tmp:
        tmp.write_bytes(encoded.tobytes())
    return path
