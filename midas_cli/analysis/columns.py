"""The aligned table's columns while they are built: one column-major block (``ColumnSet``), columns
staged by feature groups running on threads (``StagedColumns``) and the runner (``in_parallel``)."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import numpy as np

from midas_cli.errors import SessionError


class ColumnSet:
    """Aligned columns being built: name -> (N,) float64 values (NaN = masked) and metadata.

    The columns live side by side in one column-major block, so the finished table is a view of it
    (no copy of the whole table) and raw streams are gathered straight into their columns."""

    def __init__(self, n_frames: int, capacity: int = 128) -> None:
        self.n = n_frames
        self._block = np.empty((n_frames, capacity), order="F")
        self._index: dict[str, int] = {}
        self.meta: dict[str, dict[str, Any]] = {}

    @property
    def names(self) -> list[str]:
        return list(self._index)

    def claim(self, names: list[str]) -> np.ndarray:
        """(len(names), N) storage for new columns ``names`` (row j = column j), to be filled in place;
        their metadata is set with ``describe``."""
        used = len(self._index)
        if used + len(names) > self._block.shape[1]:
            grown = np.empty((self.n, max(2 * self._block.shape[1], used + len(names))), order="F")
            grown[:, :used] = self._block[:, :used]
            self._block = grown
        for k, name in enumerate(names):
            if name in self._index:
                raise SessionError(f"aligned column {name!r} computed twice")
            self._index[name] = used + k
        return self._block[:, used : used + len(names)].T

    def describe(self, name: str, unit: str = "", source: str = "", **meta: Any) -> None:
        self.meta[name] = {"unit": unit, "source": source, **{k: v for k, v in meta.items() if v}}

    def add(self, name: str, values: np.ndarray, unit: str = "", source: str = "", **meta: Any) -> None:
        values = np.asarray(values, dtype=float)
        if values.shape != (self.n,):
            raise SessionError(f"aligned column {name!r} has shape {values.shape}, expected ({self.n},)")
        self.claim([name])[0] = values  # a name added twice is an error: written columns never change
        self.describe(name, unit, source, **meta)

    def get(self, name: str) -> np.ndarray | None:
        index = self._index.get(name)
        return None if index is None else self._block[:, index]

    def stack(self, names: list[str]) -> np.ndarray:
        """(N, len(names)) of existing columns."""
        return np.column_stack([self.get(n) for n in names])

    def table(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows), C) column-major: a view of the block when every frame is kept."""
        values = self._block[:, : len(self._index)]
        return values if len(rows) == self.n else np.asfortranarray(values[rows])


class StagedColumns:
    """Columns computed against a ColumnSet without changing it, added later with ``commit``: lets
    independent feature groups run on separate threads and still land in a fixed column order."""

    def __init__(self, columns: ColumnSet) -> None:
        self.columns, self.n = columns, columns.n
        self.staged: list[tuple[str, np.ndarray, str, str, dict[str, Any]]] = []

    def get(self, name: str) -> np.ndarray | None:
        return self.columns.get(name)

    def stack(self, names: list[str]) -> np.ndarray:
        return self.columns.stack(names)

    def add(self, name: str, values: np.ndarray, unit: str = "", source: str = "", **meta: Any) -> None:
        self.staged.append((name, values, unit, source, meta))

    def commit(self) -> None:
        for name, values, unit, source, meta in self.staged:
            self.columns.add(name, values, unit, source, **meta)


def in_parallel(columns: ColumnSet, groups: list[Callable[[Any], None]]) -> None:
    """Run feature groups (each ``group(columns_like)``) on threads, then add their columns in order."""
    staged = [StagedColumns(columns) for _ in groups]
    with ThreadPoolExecutor(max_workers=max(1, min(len(groups), os.cpu_count() or 1))) as pool:
        list(pool.map(lambda pair: pair[0](pair[1]), zip(groups, staged)))
    for group in staged:
        group.commit()
