"""manifest.json: reading, validating and atomically replacing a session's manifest (format v1)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path, PurePosixPath
from typing import Any, Mapping

from midas_cli.errors import SessionError
from midas_cli.session.names import check_name, shown

SCHEMA_VERSION = 1
MANIFEST_NAME = "manifest.json"
# recording: running, or crashed (`midas session repair`); complete / interrupted: finalised by the
# recorder; recovered: repaired after a crash; failed: the recording never started (a device or OBS
# could not be opened, the disk was full): kept as a record, hidden by `session list`, refused by readers
STATUSES = ("recording", "complete", "interrupted", "recovered", "failed")
MANIFEST_TMP = MANIFEST_NAME + ".tmp"  # the temporary write_manifest renames into place
REQUIRED_KEYS = ("schema_version", "session_id", "status", "metadata", "start", "devices", "streams")


def write_manifest(folder: Path, manifest: dict[str, Any]) -> None:
    """Replace ``folder/manifest.json`` atomically: write a temp file, fsync, rename, fsync the folder.
    If the write fails (disk full) the temporary is removed and the old manifest stays as it was."""
    validate_manifest(manifest, folder)
    target = folder / MANIFEST_NAME
    tmp = folder / MANIFEST_TMP
    try:
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(manifest, fh, indent=2, sort_keys=False)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, target)
    fsync_dir(folder)


def load_manifest(folder: Path) -> dict[str, Any]:
    """Read and validate ``folder/manifest.json``; raise SessionError saying what is wrong."""
    path = Path(folder) / MANIFEST_NAME
    if not path.is_file():
        raise SessionError(f"{folder} is not a midas session: no {MANIFEST_NAME}")
    return read_manifest_file(path, Path(folder))


def read_manifest_file(path: Path, folder: Path) -> dict[str, Any]:
    """Parse and validate the manifest in ``path`` (``manifest.json``, or the temporary beside it) as
    the manifest of ``folder``; SessionError saying what is wrong."""
    try:
        manifest = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SessionError(f"cannot read {path}: {exc}") from exc
    validate_manifest(manifest, Path(folder))
    return manifest


def validate_manifest(manifest: Any, folder: Path) -> None:
    """Refuse a manifest this midas cannot read: unknown schema, a missing required key, or a field of
    the wrong JSON type (SessionError naming the field, what it holds and what it should)."""
    if not isinstance(manifest, dict):
        raise SessionError(f"manifest in {folder} is not a JSON object")
    version = manifest.get("schema_version")
    if type(version) is not int or version != SCHEMA_VERSION:
        raise SessionError(
            f"manifest in {folder} has schema_version {version!r}; this midas reads version "
            f"{SCHEMA_VERSION} only (upgrade midas to read newer sessions)"
        )
    missing = [k for k in REQUIRED_KEYS if k not in manifest]
    if missing:
        raise SessionError(f"manifest in {folder} lacks {', '.join(missing)}")
    _check_fields(manifest, TOP_FIELDS, "", folder)
    if manifest["status"] not in STATUSES:
        raise SessionError(f"manifest in {folder} has unknown status {manifest['status']!r}")
    for section, fields in (("metadata", METADATA_FIELDS), ("start", TIME_FIELDS)):
        _check_fields(manifest[section], fields, f"{section}.", folder)
    if manifest.get("stop") is not None:
        _check_fields(manifest["stop"], TIME_FIELDS, "stop.", folder)
    _check_names(manifest, folder)
    for name, device in manifest["devices"].items():
        _check_type(device, (dict,), f"devices.{name}", folder)
    for name, stream in manifest["streams"].items():
        _check_stream(name, stream, folder)
    for key, rel in (manifest.get("files") or {}).items():
        _check_type(rel, (str,), f"files.{key}", folder)
        check_inside(folder, rel, f"manifest in {folder}: files.{key}")


def _check_names(manifest: dict[str, Any], folder: Path) -> None:
    """The manifest's strings that name files (session_id, device and stream names) follow
    ``names.NAME_RULES``: a session from elsewhere cannot make a command write outside its folder."""
    where = f"manifest in {folder}:"
    check_name(manifest["session_id"], "session id", f"{where} session_id")
    for name in manifest["devices"]:
        check_name(name, "device", f"{where} a key of devices")
    for name, stream in manifest["streams"].items():
        check_name(name, "stream", f"{where} a key of streams")
        if isinstance(stream, dict) and isinstance(stream.get("device"), str):
            check_name(stream["device"], "device", f"{where} streams.{name}.device")


def _check_stream(name: str, stream: Any, folder: Path) -> None:
    if not isinstance(stream, dict) or "file" not in stream:
        raise SessionError(f"stream {name!r} in {folder} names no file")
    where = f"streams.{name}."
    _check_fields(stream, STREAM_FIELDS, where, folder)
    check_inside(folder, stream["file"], f"manifest in {folder}: {where}file")
    for k, column in enumerate(stream.get("columns") or []):
        _check_type(column, (dict,), f"{where}columns[{k}]", folder)
        _check_fields(column, COLUMN_FIELDS, f"{where}columns[{k}].", folder)
    for key, fields in (("seq_gaps", GAP_FIELDS), ("binary", BINARY_FIELDS)):
        if isinstance(stream.get(key), dict):
            _check_fields(stream[key], fields, f"{where}{key}.", folder)
    if isinstance(stream.get("binary"), dict) and "file" in stream["binary"]:
        check_inside(folder, stream["binary"]["file"], f"manifest in {folder}: {where}binary.file")


INT, FLOAT, STR, NONE = (int,), (int, float), (str,), (type(None),)
TOP_FIELDS = {"session_id": STR, "status": STR, "stop_reason": STR + NONE, "metadata": (dict,), "rig": (dict,),
              "clock": (dict,), "start": (dict,), "stop": (dict,) + NONE, "software": (dict,), "devices": (dict,),
              "streams": (dict,), "files": (dict,)}
METADATA_FIELDS = {"subject": STR + INT, "task": STR, "trial": INT, "platform": STR, "operator_note": STR,
                   "master_rate_hz": FLOAT}
TIME_FIELDS = {"utc": STR, "host_ns": INT}
STREAM_FIELDS = {"file": STR, "device": STR, "nominal_rate_hz": FLOAT + NONE, "timing": STR, "description": STR,
                 "columns": (list,), "samples": INT, "bytes": INT, "sha256": STR, "first_t_host_ns": INT + NONE,
                 "last_t_host_ns": INT + NONE, "measured_rate_hz": FLOAT + NONE, "seq_gaps": (dict,),
                 "binary": (dict,), "dropped": INT, "corrupt": INT, "latency_ms": (dict,) + NONE}
COLUMN_FIELDS = {"name": STR, "dtype": STR, "unit": STR, "decimals": INT, "clock": STR + NONE, "frame": STR + NONE,
                 "description": STR}
GAP_FIELDS = {"count": INT, "missing": INT, "resets": INT, "listed": (list,)}
BINARY_FIELDS = {"file": STR, "rows": INT, "csv_sha256": STR}
_TYPE_NAMES = {int: "an integer", float: "a number", str: "a string", dict: "an object", list: "a list",
               type(None): "null"}


def _check_fields(entry: dict[str, Any], fields: Mapping[str, tuple[type, ...]], where: str, folder: Path) -> None:
    for key, types in fields.items():
        if key in entry:
            _check_type(entry[key], types, where + key, folder)


def _check_type(value: Any, types: tuple[type, ...], where: str, folder: Path) -> None:
    """``value`` must be one of ``types`` (JSON's true/false are not numbers here; numbers are finite)."""
    ok = isinstance(value, types) and not (isinstance(value, bool) and bool not in types)
    if ok and isinstance(value, float) and not math.isfinite(value):
        ok = False
    if not ok:
        wanted = " or ".join(dict.fromkeys(_TYPE_NAMES[t] for t in types))
        raise SessionError(f"manifest in {folder}: {where} is {json.dumps(value)[:60]}, expected {wanted}; "
                           f"restore manifest.json from a copy or correct that field")


def check_inside(folder: Path, rel: Any, where: str = "manifest path") -> Path:
    """The path ``rel`` names inside the session folder; refuse absolute paths, '..', control characters
    and symlinks out (SessionError: ``where`` the path was found, and what it holds)."""
    if not isinstance(rel, str) or not rel or "\\" in rel or any(ord(c) < 32 or ord(c) == 127 for c in rel):
        raise SessionError(f"{where} {shown(rel)} is not a relative POSIX path")
    pure = PurePosixPath(rel)
    if pure.is_absolute() or ".." in pure.parts or not pure.parts:
        raise SessionError(f"{where} {shown(rel)} escapes the session folder {folder}")
    root = Path(folder).resolve()
    resolved = (root / pure).resolve()
    if root != resolved and root not in resolved.parents:
        raise SessionError(f"{where} {shown(rel)} escapes the session folder {folder} (via a link)")
    return resolved


def fsync_dir(folder: Path) -> None:
    """fsync a folder, so a rename or unlink in it survives a power loss."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
