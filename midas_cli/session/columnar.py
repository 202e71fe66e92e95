"""Binary column copies of the stream CSVs: ``streams/<name>.npy`` (session format v1, optional).

The CSV stays the archival record. When a session is finalised (recorder stop, simulate, import,
repair) each stream CSV is parsed once more and written as a NumPy structured array, one field per
CSV column in the same order, row for row: int columns as int64 (float64 with NaN where an int column
has missing values, exact below 2**53), float columns as float64 holding exactly the values a CSV
reader gets. The manifest's stream entry then carries

    "binary": {"file": "streams/<name>.npy", "rows": N, "csv_sha256": "<sha256 of the CSV it copies>"}

A reader uses the copy only while it still matches: ``csv_sha256`` equals the manifest's ``sha256``
and the CSV on disk still hashes to it (an edit that keeps the size, such as two host times swapped, is
caught; hashing costs a fraction of a parse), and the array has the CSV's columns and row count; otherwise
it parses the CSV (so a hand-edited CSV is never shadowed by a stale copy that `verify` would not
see). Analysis that reads whole streams (``midas align``) memory-maps the copy instead of parsing text.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.errors import SessionError
from midas_cli.session.manifest import check_inside
from midas_cli.session.schema import StreamSpec
from midas_cli.session.streamfile import file_sha256
from midas_cli.session.values import parse_stream_file, structured

log = logging.getLogger(__name__)

BINARY_KEY = "binary"


def binary_file(spec: StreamSpec) -> str:
    """``streams/<name>.npy``: the copy's path relative to the session folder."""
    return f"streams/{spec.name}.npy"


def parse_csv_columns(path: Path, spec: StreamSpec) -> np.ndarray:
    """Parse a stream CSV strictly (``values.parse_stream_file``: a torn last line left out) into a
    structured array (fields = the spec's columns); SessionError naming the file and line if it cannot
    be read, its header differs from the spec or a value is not of its column's type and range."""
    return structured(parse_stream_file(path, spec).frame, spec)


def write_binary_copy(folder: Path, spec: StreamSpec, csv_sha256: str) -> dict[str, Any]:
    """Write ``streams/<name>.npy`` from the stream's CSV (via a temporary file and rename) and return
    the manifest's ``binary`` entry."""
    table = parse_csv_columns(Path(folder) / spec.file, spec)
    target = Path(folder) / binary_file(spec)
    tmp = target.with_name(target.name + ".tmp")
    try:
        with open(tmp, "wb") as fh:
            np.save(fh, table, allow_pickle=False)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except OSError:  # disk full, file-size limit: no copy, nothing half-written left behind
        tmp.unlink(missing_ok=True)
        raise
    return {"file": binary_file(spec), "rows": int(len(table)), "csv_sha256": csv_sha256}


def add_binary_copies(folder: Path, manifest: dict[str, Any]) -> None:
    """Give every stream of a finished ``manifest`` its binary copy (entries updated in place). A stream
    whose CSV cannot be parsed (damaged lines), or whose copy cannot be written (disk full), keeps none;
    readers then parse the CSV."""
    for name, entry in manifest["streams"].items():
        spec = StreamSpec.from_manifest(name, entry)
        try:
            entry[BINARY_KEY] = write_binary_copy(Path(folder), spec, entry["sha256"])
        except (SessionError, KeyError, OSError, ValueError, MemoryError) as exc:
            entry.pop(BINARY_KEY, None)
            log.warning("no binary copy of stream %s: %s", name, exc)


def load_binary_copy(folder: Path, name: str, entry: dict[str, Any]) -> np.ndarray | None:
    """The stream's copy memory-mapped read-only, or None when there is none or it no longer matches
    its CSV (see the module docstring)."""
    binary = entry.get(BINARY_KEY)
    if not isinstance(binary, dict) or binary.get("csv_sha256") != entry.get("sha256"):
        return None
    csv_path, copy_path = check_inside(Path(folder), entry["file"]), check_inside(Path(folder), binary.get("file", ""))
    if not copy_path.is_file():
        return None  # deleted (the remedy `verify` suggests for a bad copy): the CSV is read
    try:
        if csv_path.stat().st_size != entry.get("bytes") or file_sha256(csv_path) != binary["csv_sha256"]:
            return None
        table = np.load(copy_path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, KeyError) as exc:
        log.warning("binary copy of stream %s unusable (%s); reading the CSV", name, exc)
        return None
    spec = StreamSpec.from_manifest(name, entry)
    if table.dtype.names != tuple(spec.column_names) or len(table) != binary.get("rows"):
        return None
    return table


def copy_differences(folder: Path, name: str, entry: dict[str, Any], parsed: np.ndarray | None = None) -> list[str]:
    """What is wrong with a stream's binary copy, checked against its CSV (``parsed``, or parsed again)
    (for `verify`); empty when the stream has none or it matches exactly."""
    binary = entry.get(BINARY_KEY)
    if binary is None or not check_inside(Path(folder), binary.get("file", "")).is_file():
        return []  # none, or deleted: readers parse the CSV
    remedy = "delete it and readers parse the CSV"
    try:
        copy = np.load(check_inside(Path(folder), binary["file"]), mmap_mode="r", allow_pickle=False)
        if parsed is None:
            parsed = parse_csv_columns(check_inside(Path(folder), entry["file"]), StreamSpec.from_manifest(name, entry))
    except (OSError, ValueError, KeyError, TypeError, SessionError) as exc:
        return [f"binary copy {binary.get('file')!r} unreadable ({exc}); {remedy}"]
    if binary.get("csv_sha256") != entry.get("sha256"):
        return [f"binary copy {binary['file']} was made from another version of the CSV; {remedy}"]
    fields = parsed.dtype.names or ()
    same = copy.dtype.names == parsed.dtype.names and len(copy) == len(parsed) and all(
        np.array_equal(copy[f], parsed[f], equal_nan=parsed[f].dtype.kind == "f") for f in fields)
    return [] if same else [f"binary copy {binary['file']} differs from the CSV; {remedy}"]
