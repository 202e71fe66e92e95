"""manifest.json: reading, validating and atomically replacing a session's manifest (format v1)."""

from __future__ import annotations

import json
import os
from pathlib import Path, PurePosixPath
from typing import Any

from midas_cli.errors import SessionError

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
    if not isinstance(manifest, dict):
        raise SessionError(f"manifest in {folder} is not a JSON object")
    version = manifest.get("schema_version")
    if version != SCHEMA_VERSION:
        raise SessionError(
            f"manifest in {folder} has schema_version {version!r}; this midas reads version "
            f"{SCHEMA_VERSION} only (upgrade midas to read newer sessions)"
        )
    missing = [k for k in REQUIRED_KEYS if k not in manifest]
    if missing:
        raise SessionError(f"manifest in {folder} lacks {', '.join(missing)}")
    if manifest["status"] not in STATUSES:
        raise SessionError(f"manifest in {folder} has unknown status {manifest['status']!r}")
    for name, stream in manifest["streams"].items():
        if not isinstance(stream, dict) or "file" not in stream:
            raise SessionError(f"stream {name!r} in {folder} names no file")
        check_inside(folder, stream["file"])
    for rel in manifest.get("files", {}).values():
        check_inside(folder, rel)


def check_inside(folder: Path, rel: Any) -> Path:
    """The path ``rel`` names inside the session folder; refuse absolute paths, '..' and symlinks out."""
    if not isinstance(rel, str) or not rel or "\\" in rel or "\0" in rel:
        raise SessionError(f"manifest path {rel!r} is not a relative POSIX path")
    pure = PurePosixPath(rel)
    if pure.is_absolute() or ".." in pure.parts:
        raise SessionError(f"manifest path {rel!r} escapes the session folder {folder}")
    root = Path(folder).resolve()
    resolved = (root / pure).resolve()
    if root != resolved and root not in resolved.parents:
        raise SessionError(f"manifest path {rel!r} escapes the session folder {folder} (via a link)")
    return resolved


def fsync_dir(folder: Path) -> None:
    """fsync a folder, so a rename or unlink in it survives a power loss."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
