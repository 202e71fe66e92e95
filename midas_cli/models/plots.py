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


def write_confusion_png(path: Path, matrix: np.ndarray, classes: Sequence[str], cell: int = 56) -> Path:
    """Row-normalised confusion matrix (rows = truth, columns = prediction) with counts, as a PNG."""
    n = len(classes)
    margin = 90
    image = np.full((margin + n * cell + 40, margin + n * cell + 20, 3), 255, np.uint8)
    rows = matrix.sum(axis=1, keepdims=True)
    share = np.divide(matrix, rows, out=np.zeros(matrix.shape, float), where=rows > 0)
    for i in range(n):
        for j in range(n):
            shade = int(255 * (1 - share[i, j]))
            top_left = (margin + j * cell, margin + i * cell)
            cv2.rectangle(image, top_left, (top_left[0] + cell - 1, top_left[1] + cell - 1), (255, shade, shade), -1)
            colour = WHITE if share[i, j] > 0.5 else BLACK
            cv2.putText(image, str(int(matrix[i, j])), (top_left[0] + 4, top_left[1] + cell // 2 + 5), FONT, 0.4, colour, 1)
        cv2.putText(image, classes[i][:10], (4, margin + i * cell + cell // 2 + 5), FONT, 0.45, BLACK, 1)
        cv2.putText(image, classes[i][:7], (margin + i * cell + 2, margin - 8), FONT, 0.45, BLACK, 1)
    cv2.putText(image, "truth (rows) x prediction (columns)", (margin, margin + n * cell + 25), FONT, 0.45, BLACK, 1)
    return _save(path, image)


def write_timeline_png(path: Path, truth: np.ndarray, prediction: np.ndarray, classes: Sequence[str],
                       title: str, width: int = 1000) -> Path:
    """Two colour ribbons over time: ground truth (top) and prediction (bottom, grey = not tested)."""
    colours = class_colours(len(classes))
    band, top = 40, 30
    legend_rows = (len(classes) + 5) // 6
    image = np.full((top + 2 * band + 30 + 22 * legend_rows, width + 110, 3), 255, np.uint8)
    cv2.putText(image, title[:90], (5, 20), FONT, 0.5, BLACK, 1)
    for row, (name, labels) in enumerate((("truth", truth), ("predicted", prediction))):
        y0 = top + row * (band + 10)
        cv2.putText(image, name, (5, y0 + band // 2 + 5), FONT, 0.45, BLACK, 1)
        columns = (np.arange(width) * len(labels) // width) if len(labels) else np.zeros(0, int)
        for x, idx in enumerate(columns):
            label = labels[idx]
            cv2.line(image, (100 + x, y0), (100 + x, y0 + band), colours[label] if label >= 0 else GREY, 1)
    for k, name in enumerate(classes):
        x0, y0 = 100 + (k % 6) * 150, top + 2 * band + 30 + (k // 6) * 22
        cv2.rectangle(image, (x0, y0 - 12), (x0 + 14, y0 + 2), colours[k], -1)
        cv2.putText(image, name[:14], (x0 + 20, y0), FONT, 0.45, BLACK, 1)
    return _save(path, image)


def _save(path: Path, image: np.ndarray) -> Path:
    path = Path(path)
    ok, encoded = cv2.imencode(path.suffix or ".png", image)
    if not ok:
        raise SessionError(f"cannot write {path}: no image format for {path.suffix!r}")
    with replacing(out_target(path)) as tmp:
        tmp.write_bytes(encoded.tobytes())
    return path
