"""Is a session's aligned table older than what it was made from?

``midas align`` records in ``derived/aligned.json`` (``producer.inputs``) each stream file's sha256 and
size as the manifest gave them, and each calibration file's. The table is stale when, since then,

* the manifest names a stream file the table was not made from, or no longer names one it was;
* the manifest's sha256 or size of a stream file differs from the recorded one (recorded again,
  repaired, re-imported);
* a stream or calibration file's size on disk differs from the recorded one, or the file is newer than
  the table and its bytes no longer hash to the recorded sha256 (an edit that keeps the size; a copy
  that only touched the modification times is hashed once per read and passes).

Tables that record no inputs (an older midas, a table written by other code) cannot be checked
and are taken as they are.
"""

from __future__ import annotations

import shlex
import stat
from pathlib import Path
from typing import Any

from midas_cli.session.manifest import check_inside
from midas_cli.session.streamfile import file_sha256

# AlignOptions field -> the `midas align` option that sets it, and the value it has by default
ALIGN_FLAGS = {"method": ("--method", "causal"), "rate_hz": ("--downsample", None),
               "clock_hz": ("--clock", None), "model": ("--calibration-model", "best")}


def changed_inputs(folder: Path, manifest: dict[str, Any], meta: dict[str, Any], made_ns: int) -> list[str]:
    """The inputs of the aligned table (``meta``: aligned.json, written at ``made_ns``, st_mtime_ns)
    that changed since, as ``streams/emht.csv (the file)``-like phrases; empty when none did or the
    table records no inputs (a midas before they were recorded, a table written without them)."""
    producer = meta.get("producer") if isinstance(meta, dict) else None
    inputs = producer.get("inputs") if isinstance(producer, dict) else None
    if not inputs:
        return []
    if not _well_formed(inputs):
        return ["derived/aligned.json (its producer.inputs is not a map of file -> {sha256, bytes})"]
    now = {entry["file"]: entry for entry in manifest["streams"].values()}
    changed = {rel: "not in the manifest any more" for rel in inputs if not rel.startswith("calib/") and rel not in now}
    for rel, entry in now.items():
        if rel not in inputs:
            changed[rel] = "new in the manifest"
        elif any(entry.get(k) != inputs[rel].get(k) for k in ("sha256", "bytes")):
            changed[rel] = "its sha256 or size in the manifest"
    for rel, recorded in inputs.items():
        if rel not in changed and _file_changed(folder, rel, recorded, made_ns):
            changed[rel] = "the file"
    return [f"{rel} ({why})" for rel, why in changed.items()]


def _well_formed(inputs: Any) -> bool:
    """Whether ``producer.inputs`` of aligned.json is a map of file -> {sha256: str|None, bytes: int|None}."""
    return isinstance(inputs, dict) and all(
        isinstance(rel, str) and isinstance(v, dict) and isinstance(v.get("sha256"), (str, type(None)))
        and isinstance(v.get("bytes"), (int, type(None))) and not isinstance(v.get("bytes"), bool)
        for rel, v in inputs.items())


def _file_changed(folder: Path, rel: str, recorded: dict[str, Any], made_ns: int) -> bool:
    """Whether the file ``rel`` of the session differs from ``recorded`` ({sha256, bytes}): missing, not
    a regular file, another size, or newer than the table and hashing to another sha256."""
    path = check_inside(folder, rel)
    try:
        found = path.stat()
    except OSError:
        return True
    if not stat.S_ISREG(found.st_mode):  # a FIFO or device is never opened (a read could block for ever)
        return True
    if recorded.get("bytes") is not None and found.st_size != recorded["bytes"]:
        return True
    if found.st_mtime_ns <= made_ns or recorded.get("sha256") is None:
        return False
    try:
        return file_sha256(path) != recorded["sha256"]
    except OSError:
        return True


def align_command(folder: Path, meta: dict[str, Any], csv: bool) -> str:
    """``midas align FOLDER [options]`` with the options the table was made with (when it says), and
    ``--csv`` when ``csv`` (the table has its CSV beside it)."""
    producer = meta.get("producer") if isinstance(meta, dict) else None
    options = producer.get("options") if isinstance(producer, dict) else None
    words = ["midas", "align", str(folder)]
    for field, (flag, default) in ALIGN_FLAGS.items():
        value = options.get(field, default) if isinstance(options, dict) else default
        if value != default and isinstance(value, (str, int, float)) and not isinstance(value, bool):
            words += [flag, f"{value:g}" if isinstance(value, float) else str(value)]
    return shlex.join(words + (["--csv"] if csv else []))
