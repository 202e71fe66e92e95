"""A session folder appears whole or not at all.

`make_session_folder` builds the new folder in the output folder's hidden staging folder
(``<out>/.midas-new/<pid>-<start>-<random>/``, the same file system), lets the caller write into it (the
"recording" manifest first), and only then renames it to ``<out>/<stem>_<YYYYMMDDTHHMMSSZ>``: a recorder
killed at any instant of its start leaves either a session that `midas session repair` understands or no
session at all, and whoever watches ``<out>/*/manifest.json`` never sees a manifest that is about to
move. What such a kill can leave is its folder under ``.midas-new/``: it holds no recorded data
(streams are written only once the folder has its name), readers and `session list` skip it, and the
next session made in the same output folder removes the folders of processes that have ended (and
``.midas-new`` itself once it is empty).
"""

from __future__ import annotations

import errno
import logging
import os
import re
import secrets
import shutil
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

from midas_cli.errors import SessionError
from midas_cli.processes import process_start
from midas_cli.session.manifest import fsync_dir

log = logging.getLogger(__name__)

STAGING_DIR = ".midas-new"  # in the output folder: where session folders are made
_STAGING = re.compile(r"(\d+)-(\d*)-[0-9a-f]{8}")  # a folder being made: its maker's PID and start time
MAX_CLASHES = 1000


def make_session_folder(out_root: Path, stem: str, host_ns: int,
                        populate: Callable[[Path, str], None]) -> Path:
    """Create ``out_root/<stem>_<YYYYMMDDTHHMMSSZ>`` holding what ``populate(folder, name)`` wrote,
    and return it. Never reuses a folder (a clash gets _2, _3, ...); ``populate`` is called again with
    the new name after a clash, so it must be repeatable. SessionError when the folder cannot be made;
    whatever ``populate`` raises propagates, and nothing is left behind either way (short of a kill)."""
    out_root = Path(out_root)
    stamp = datetime.fromtimestamp(host_ns / 1e9, tz=timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    try:
        out_root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SessionError(f"cannot create output folder {out_root}: {exc.strerror}") from exc
    remove_stale_staging(out_root)
    staging = _make_staging(out_root)
    try:
        return _claim_name(staging, out_root, f"{stem}_{stamp}", populate)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    finally:
        _remove_if_empty(out_root / STAGING_DIR)


def _make_staging(out_root: Path) -> Path:
    pid = os.getpid()
    name = f"{pid}-{process_start(pid) or ''}-{secrets.token_hex(4)}"
    for _ in range(100):  # another start may remove the empty staging folder between the two mkdirs
        try:
            _staging_root(out_root).mkdir(exist_ok=True)
            (out_root / STAGING_DIR / name).mkdir()
            return out_root / STAGING_DIR / name
        except FileNotFoundError:
            continue
        except OSError as exc:
            raise SessionError(f"cannot create a session folder in {out_root}: {exc.strerror}") from exc
    raise SessionError(f"cannot create a session folder in {out_root}: its {STAGING_DIR} keeps vanishing")


def _staging_root(out_root: Path) -> Path:
    """``out_root/.midas-new``; SessionError if it is a link (folders found there get removed: never
    follow one out of the output folder)."""
    root = out_root / STAGING_DIR
    if root.is_symlink():
        raise SessionError(f"{root} is a link; midas makes session folders there: remove it")
    return root


def _claim_name(staging: Path, out_root: Path, base: str, populate: Callable[[Path, str], None]) -> Path:
    for attempt in range(1, MAX_CLASHES):
        name = base if attempt == 1 else f"{base}_{attempt}"
        folder = out_root / name
        if os.path.lexists(folder):
            continue
        populate(staging, name)
        try:
            os.rename(staging, folder)  # replaces nothing but an empty folder made in between
        except OSError as exc:
            if exc.errno in (errno.EEXIST, errno.ENOTEMPTY, errno.ENOTDIR):
                continue  # another recorder took the name between the check and the rename
            raise SessionError(f"cannot create session folder {folder}: {exc.strerror}") from exc
        fsync_dir(out_root)
        return folder
    raise SessionError(f"too many sessions named {base} in {out_root}")


def _remove_if_empty(folder: Path) -> None:
    try:
        folder.rmdir()
    except OSError:  # not empty (another start is making its session there), or gone already
        pass


def remove_stale_staging(out_root: Path) -> list[Path]:
    """Remove the folders in ``out_root``'s staging folder whose process has ended (killed while it made
    a session: they hold no recorded data); return them. Another process's folder being made is kept."""
    removed: list[Path] = []
    try:
        entries = list(os.scandir(_staging_root(Path(out_root))))
    except OSError:
        return removed
    for entry in entries:
        match = _STAGING.fullmatch(entry.name)
        if not match or not entry.is_dir(follow_symlinks=False):
            continue
        pid, started = int(match.group(1)), match.group(2)
        now = process_start(pid)
        if now is not None and (not started or not now or now == started):
            continue  # its maker still runs (a reused PID has another start time)
        shutil.rmtree(entry.path, ignore_errors=True)
        log.info("removed %s, left by a session start that was killed", entry.path)
        removed.append(Path(entry.path))
    return removed
