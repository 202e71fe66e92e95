"""Derived files of a session: ``derived/aligned.{npz,values.npy,json}`` (+ ``.csv`` on request), ``calib/*`` and ``derived/eval/``.

Only this module (with the rest of ``midas_cli/session/``) knows where these files live.

Aligned table (written by ``midas align``):
  * ``derived/aligned.npz``: ``frame`` (N,) int64 video frame index (= video ``seq``), ``t_host_ns``
    (N,) int64 frame time on the host clock, ``columns`` (C,) str.
  * ``derived/aligned.values.npy``: (N, C) float64, column-major, NaN where masked (the mask, True =
    valid sample, is ``isfinite(values)``).
  * ``derived/aligned.csv`` (only with ``midas align --csv``): ``frame,t_host_ns,<columns>``; a masked
    value is an empty field.
  * ``derived/aligned.json``: column metadata (unit, frame, source, description), method, rate, source
    stream sha256s, calibrations applied, and ``producer`` (outputs.provenance: run_id, command,
    options, inputs, midas version, time).

The three files of one run share its ``run_id``: ``aligned.npz`` holds it as ``run_id``, the JSON as
``producer.run_id``, and ``aligned.values.npy`` in a trailer after the array data (``RUN_TRAILER`` + 32
hex digits + newline; NumPy reads the array and ignores what follows it). ``read_aligned`` and
``session verify`` refuse files of different runs. Written under the session lock, each via a unique
temporary renamed into place, so two ``midas align`` runs on one session leave one run's files.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import threading
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import pandas as pd

from midas_cli.errors import SessionError
from midas_cli.session.freshness import align_command, changed_inputs
from midas_cli.session.manifest import load_manifest
from midas_cli.session.outputs import (provenance, replacing, session_folder, session_lock, session_read_lock,
                                       session_target, temporary_beside)

ALIGNED_STEM = "derived/aligned"
CALIB_DIR = "calib"
EVAL_DIR = "derived/eval"
PLOTS_DIR = "derived/plots"
PEDALS_GT = "derived/pedals_gt.csv"
RUN_TRAILER = b"MIDAS-RUN:"
_TRAILER_LEN = len(RUN_TRAILER) + 32 + 1


@dataclass
class AlignedTable:
    """Every stream on the video frame clock: ``values`` (N, C) float64, NaN where masked."""

    frame: np.ndarray
    t_host_ns: np.ndarray
    columns: list[str]
    values: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    @functools.cached_property
    def mask(self) -> np.ndarray:
        """(N, C) bool, True = valid sample (computed on first use: a pass over every value)."""
        return np.isfinite(self.values)

    def column(self, name: str) -> np.ndarray:
        """One column (N,) float64, NaN where masked."""
        try:
            return self.values[:, self.columns.index(name)]
        except ValueError:
            raise SessionError(f"aligned table has no column {name!r}; re-run `midas align` "
                               f"(columns start: {', '.join(self.columns[:8])}, ...)") from None

    def has(self, name: str) -> bool:
        return name in self.columns

    def times_s(self) -> np.ndarray:
        """Frame times (N,) in seconds since the first frame."""
        return (self.t_host_ns - self.t_host_ns[0]) / 1e9 if len(self.t_host_ns) else np.zeros(0)


class ValuesFile:
    """``derived/aligned.values.npy`` written while the table is still being built: columns that are
    final are appended on a background thread while later ones are computed (the kernel's copy of the
    file overlaps the computation on a second core), and the header gets the final column count last.
    Until ``write_aligned`` renames it into place the file is a unique ``.aligned.values.npy.*.tmp``
    (the caller holds the session lock while it exists)."""

    def __init__(self, session_path: Path | str, n_rows: int) -> None:
        target = session_target(session_path, f"{ALIGNED_STEM}.values.npy")
        self.path = temporary_beside(target)
        self.n_rows, self.columns_written = n_rows, 0
        self._fh = open(self.path, "wb")
        self._fh.write(_npy_header(n_rows, 0))
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def write_async(self, block: np.ndarray) -> None:
        """Append the columns of ``block`` ((N, k), column-major: left untouched until ``finish``)."""
        self._join()
        self._thread = threading.Thread(target=self._write, args=(block,), name="aligned-values", daemon=True)
        self._thread.start()
        self.columns_written += block.shape[1]

    def finish(self, values: np.ndarray, run_id: str) -> None:
        """Append the columns of ``values`` (N, C) not written yet and the run trailer, and write the
        final header."""
        self._join()
        self._write(values[:, self.columns_written :])
        if self._error is not None:
            raise self._error
        self._fh.write(_trailer(run_id))
        self._fh.seek(0)
        self._fh.write(_npy_header(self.n_rows, values.shape[1]))
        self._fh.close()

    def abort(self) -> None:
        self._join()
        self._fh.close()
        self.path.unlink(missing_ok=True)

    def _write(self, block: np.ndarray) -> None:
        try:
            self._fh.write(np.asfortranarray(block).T.data)  # (k, N) C-contiguous: column after column
        except BaseException as exc:  # re-raised in the caller's thread by finish()
            self._error = exc

    def _join(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None


def _npy_header(n_rows: int, n_columns: int) -> bytes:
    """NPY 1.0 header of a (n_rows, n_columns) column-major float64 array, the same length whatever
    ``n_columns`` is (< 10**10), so the final count can overwrite a provisional one in place."""
    text = "{'descr': '<f8', 'fortran_order': True, 'shape': (%d, %-10d), }" % (n_rows, n_columns)
    total = -(-(10 + len(text) + 1) // 64) * 64
    text = text.ljust(total - 10 - 1) + "\n"
    return b"\x93NUMPY\x01\x00" + len(text).to_bytes(2, "little") + text.encode("latin1")


def write_aligned(session_path: Path | str, table: AlignedTable, csv: bool = False,
                  values_file: ValuesFile | None = None) -> dict[str, Path]:
    """Write ``derived/aligned.npz``, ``aligned.values.npy``, ``aligned.json`` (and ``aligned.csv`` when
    ``csv``), under the session lock, each via a unique temporary and rename, all stamped with the run
    id of ``table.meta["producer"]`` (made here if missing). The values go to their own column-major
    ``.npy`` in one write (no zip CRC, no copy), which a reader can memory-map and read column by
    column. A CSV from an earlier run is removed when ``csv`` is off, so no stale table is left beside
    the new one."""
    producer = table.meta.setdefault("producer", provenance("midas align", {}, {}))
    run_id = producer["run_id"]
    with session_lock(session_path), contextlib.ExitStack() as stack:
        paths = {ext: session_target(session_path, f"{ALIGNED_STEM}.{ext}")
                 for ext in ("values.npy", "npz", "json", *(("csv",) if csv else ()))}
        tmps = {ext: stack.enter_context(replacing(path)) for ext, path in paths.items()}
        if values_file is not None:
            values_file.finish(table.values, run_id)
            os.replace(values_file.path, tmps["values.npy"])
        else:
            with open(tmps["values.npy"], "wb") as fh:
                np.save(fh, np.asfortranarray(table.values), allow_pickle=False)
                fh.write(_trailer(run_id))
        with open(tmps["npz"], "wb") as fh:
            np.savez(fh, frame=table.frame, t_host_ns=table.t_host_ns,
                     columns=np.asarray(table.columns, dtype=str), run_id=np.asarray(run_id))
        if csv:
            write_aligned_csv(tmps["csv"], table)
        tmps["json"].write_text(json.dumps(table.meta, indent=2) + "\n", encoding="utf-8")
        if not csv:  # under the same lock: a concurrent `align --csv` cannot lose its CSV to this run
            paths["values.npy"].with_name("aligned.csv").unlink(missing_ok=True)
        # leaving the stack renames the temporaries into place (json first, values last: reversed order)
    return paths


def _trailer(run_id: str) -> bytes:
    return RUN_TRAILER + run_id.encode("ascii") + b"\n"


def values_run_id(path: Path) -> str | None:
    """The run id in the trailer of an ``aligned.values.npy``; None when it has none (older midas)."""
    with open(path, "rb") as fh:
        fh.seek(0, os.SEEK_END)
        if fh.tell() < _TRAILER_LEN:
            return None
        fh.seek(-_TRAILER_LEN, os.SEEK_END)
        tail = fh.read()
    if not tail.startswith(RUN_TRAILER) or not tail.endswith(b"\n"):
        return None
    return tail[len(RUN_TRAILER):-1].decode("ascii", "replace")


def write_aligned_csv(path: Path, table: AlignedTable) -> None:
    """``frame,t_host_ns,<columns>`` with 6 significant digits; a masked value is an empty field."""
    import pandas as pd

    frame = pd.DataFrame(np.where(table.mask, table.values, np.nan), columns=table.columns)
    frame.insert(0, "t_host_ns", table.t_host_ns)
    frame.insert(0, "frame", table.frame)
    frame.to_csv(path, index=False, float_format="%.6g")


def aligned_files(session_path: Path | str) -> list[Path]:
    """The files of the session's aligned table (``derived/aligned.npz|values.npy|json|csv``): what a
    command reading it reads, so what its ``--out`` must never be."""
    base = Path(session_path) / ALIGNED_STEM
    return [base.with_suffix(s) for s in (".npz", ".values.npy", ".json", ".csv")]


def read_aligned(session_path: Path | str, current: bool = True) -> AlignedTable:
    """Read ``derived/aligned.*``; SessionError if ``midas align`` has not run, or (``current``) when the
    session's manifest is not valid or the table is older than its streams or calibrations. The values
    are memory-mapped read-only (tables written before they had their own file come from the npz)."""
    base = Path(session_path) / ALIGNED_STEM
    npz_path, values_path, json_path = (base.with_suffix(s) for s in (".npz", ".values.npy", ".json"))
    if not npz_path.is_file():
        raise SessionError(f"{session_path} has no {npz_path.name}: run `midas align {session_path}` first")
    try:
        with session_read_lock(session_path), np.load(npz_path, allow_pickle=False) as data:
            frame, t_host_ns, columns = data["frame"], data["t_host_ns"], data["columns"].tolist()
            run_id = str(data["run_id"]) if "run_id" in data.files else None
            if "values" in data.files:
                values, values_run = data["values"], run_id
            else:
                values, values_run = np.load(values_path, mmap_mode="r"), values_run_id(values_path)
            meta = json.loads(json_path.read_text(encoding="utf-8")) if json_path.is_file() else {}
            made_ns = json_path.stat().st_mtime_ns if json_path.is_file() else npz_path.stat().st_mtime_ns
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:  # damaged or not an npz at all
        raise SessionError(f"cannot read {npz_path}: {exc} (re-run `midas align {session_path}`)") from exc
    json_run = (meta.get("producer") or {}).get("run_id") if isinstance(meta, dict) else None
    if run_id is not None or values_run is not None or json_run is not None:
        if not run_id == values_run == json_run:
            raise SessionError(f"{base.parent}: aligned.npz, aligned.values.npy and aligned.json come from different "
                               f"`midas align` runs (run ids {run_id}, {values_run}, {json_run}): "
                               f"re-run `midas align {session_path}`")
    if values.shape != (len(frame), len(columns)):
        raise SessionError(f"{values_path} holds {values.shape} values for {len(frame)} frames x {len(columns)} "
                           f"columns: re-run `midas align {session_path}`")
    if current:
        _refuse_stale(Path(session_path), meta, made_ns)
    return AlignedTable(frame, t_host_ns, columns, values, meta)


def _refuse_stale(folder: Path, meta: dict[str, Any], made_ns: int) -> None:
    """SessionError, with the exact `midas align` command to run, when the session's manifest is not
    valid or an input of the aligned table changed after it was made (``freshness.changed_inputs``)."""
    changed = changed_inputs(folder, load_manifest(folder), meta, made_ns)
    if changed:
        csv = (folder / f"{ALIGNED_STEM}.csv").is_file()
        raise SessionError(f"{folder}: derived/aligned was made before {'; '.join(changed)} changed: run "
                           f"`{align_command(folder, meta, csv)}` to align it again")


def aligned_problems(session_path: Path | str) -> list[str]:
    """What is wrong with the session's aligned table, for `session verify` (nothing when it has none)."""
    if not (Path(session_path) / f"{ALIGNED_STEM}.npz").is_file():
        return []
    try:
        read_aligned(session_path, current=False)  # integrity only: an older table is not damage
    except SessionError as exc:
        return [str(exc)]
    return []


def calib_path(session_path: Path | str, name: str) -> Path:
    """``calib/<name>`` inside the session (the folder is created if missing; refused if it leads out)."""
    return session_target(session_path, f"{CALIB_DIR}/{name}")


def find_calibration(session_path: Path | str, name: str) -> Path | None:
    """``calib/<name>`` if it exists, else None."""
    path = Path(session_path) / CALIB_DIR / name
    return path if path.is_file() else None


def output_dir(session_path: Path | str, kind: str) -> Path:
    """``derived/eval`` (kind "eval") or ``derived/plots`` (kind "plots"), created if missing."""
    return session_folder(session_path, {"eval": EVAL_DIR, "plots": PLOTS_DIR}[kind])


def read_pedals_ground_truth(session_path: Path | str) -> pd.DataFrame | None:
    """``derived/pedals_gt.csv`` (frame, t_host_ns, one 0/1 column per pedal name) or None if absent."""
    path = Path(session_path) / PEDALS_GT
    if not path.is_file():
        return None
    import pandas as pd

    try:
        frame = pd.read_csv(path)
    except (OSError, ValueError, pd.errors.ParserError) as exc:
        raise SessionError(f"cannot read {path}: {exc}") from exc
    if "frame" not in frame.columns:
        raise SessionError(f"{path} has no 'frame' column (columns: {', '.join(frame.columns)})")
    return frame

