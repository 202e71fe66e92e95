"""Where midas writes, and how: every output path is resolved and checked, every file is written under
a unique temporary name and renamed into place, under the session's lock.

* ``session_target(session, "derived/x.csv")``: a file midas itself places inside a session (derived/,
  labels/, calib/). The path is resolved; one that leaves the session (``derived/`` a link to another
  folder, a ``..``) or names a file the session owns is refused (SessionError, exit 4) before anything
  is created.
* ``out_target(path)``: a file named by the user (``--out``, ``--plot``). It may be anywhere, but never a
  file a session owns: ``manifest.json`` (and its temporary), the lock file, anything under
  ``streams/``, ``video/`` or ``logs/``, and any file the manifest lists, nor one of the files the
  command reads (its ``inputs``: ``labels export --out`` is never the label set it exports) (ConfigError,
  exit 2). A missing parent folder is created (as ``eval --out`` and ``train --out`` always did); one
  that cannot be is ConfigError.
* ``out_child(folder, name)``: a file in an output folder whose name comes from the data (``<session
  id>.mcap``, ``predictions/<trial>.csv``): ``name`` must be one plain file name that stays in the
  folder (SessionError, exit 4), then it is checked as ``out_target``. Sessions' names are checked when
  they are read (``names.py``); this is the writers' own guard.
* ``replacing(target)``: yields a unique temporary beside ``target`` (``.<name>.<random>.tmp``: two runs
  never share one; ``session verify`` reports and ``session repair`` removes them if a run is killed),
  renames it over ``target`` when the block succeeds and removes it when it fails. Held under the lock
  of the session ``target`` is in, if any.
* ``session_lock(session)``: ``fcntl.flock`` on ``<session>/.midas.lock``. A second midas writing the
  same session waits (saying so on stderr, once) up to ``MIDAS_LOCK_WAIT_S`` seconds (default 600),
  then gives up with SessionError (exit 4). The kernel drops the lock when its holder dies, so a killed
  run never blocks the next one. The file stays, empty and never rewritten (it is not litter, and a
  session's files do not change by being locked). Re-entrant within a process.
* ``provenance(command, options, inputs)``: what a derived file records about the run that made it.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import logging
import os
import socket
import tempfile
import threading
import time
import uuid
from datetime import datetime, timezone
from pathlib import Path, PurePosixPath
from typing import Any, Iterable, Iterator

from midas_cli import __version__
from midas_cli.errors import ConfigError, MidasError, SessionError
from midas_cli.session.manifest import MANIFEST_NAME, MANIFEST_TMP
from midas_cli.session.names import shown

log = logging.getLogger(__name__)

LOCK_NAME = ".midas.lock"
LOCK_WAIT_ENV = "MIDAS_LOCK_WAIT_S"
LOCK_WAIT_DEFAULT_S = 600.0
LOCK_POLL_S = 0.05
OWNED_FILES = (MANIFEST_NAME, MANIFEST_TMP, LOCK_NAME)
OWNED_DIRS = ("streams", "video", "logs")  # the recording itself: no derived output goes there

_UMASK = os.umask(0o022)
os.umask(_UMASK)
_held: dict[Path, list[int]] = {}  # resolved session -> [lock fd, depth] held by this process
_held_guard = threading.Lock()


# ---- which session a path is in, and what it owns -------------------------------------------------

def session_of(path: Path | str) -> Path | None:
    """The (resolved) session folder ``path`` lies in: the nearest folder at or above it holding a
    ``manifest.json``; None when there is none."""
    resolved = Path(path).resolve()
    for folder in (resolved, *resolved.parents):
        if (folder / MANIFEST_NAME).is_file():
            return folder
    return None


def owned_files(session: Path) -> set[str]:
    """Paths (relative, POSIX) of the files ``session`` owns beyond the fixed ones: every file its
    manifest lists (stream CSVs, their binary copies, ``files``). Empty when the manifest is unreadable."""
    try:
        manifest = json.loads((Path(session) / MANIFEST_NAME).read_text(encoding="utf-8"))
        listed = set()
        for entry in (manifest.get("streams") or {}).values():
            listed.add(entry.get("file"))
            listed.add((entry.get("binary") or {}).get("file"))
        listed.update((manifest.get("files") or {}).values())
    except (OSError, ValueError, AttributeError, TypeError):
        return set()
    return {PurePosixPath(p).as_posix() for p in listed if isinstance(p, str) and p}


def _owned_reason(session: Path, resolved: Path) -> str | None:
    rel = resolved.relative_to(session)
    if rel == Path("."):
        return "the session folder itself"
    if rel.as_posix() in OWNED_FILES or rel.parts[0] in OWNED_DIRS:
        return f"{rel.as_posix()}, part of the recording"
    if rel.as_posix() in owned_files(session):
        return f"{rel.as_posix()}, listed in its manifest"
    return None


# ---- output paths ------------------------------------------------------------------------------

def session_target(session: Path | str, relative: str) -> Path:
    """The resolved path of ``relative`` inside ``session``, its folder created; SessionError (nothing
    created) when it would leave the session (a linked folder, '..') or names a file the session owns."""
    resolved = _resolve_inside(session, relative)
    reason = _owned_reason(Path(session).resolve(), resolved)
    if reason is not None:
        raise SessionError(f"refusing to write {relative}: it is {reason} of {session}")
    _make_parent(resolved, SessionError)
    return resolved


def inside_session(session: Path | str, relative: str) -> Path:
    """Like ``session_target`` for the writers of the recording itself (import reports in logs/, a
    stream an offline step adds): confined to the session, but may name a file it owns."""
    resolved = _resolve_inside(session, relative)
    _make_parent(resolved, SessionError)
    return resolved


def _resolve_inside(session: Path | str, relative: str) -> Path:
    pure = PurePosixPath(relative)
    root = Path(session).resolve()
    if pure.is_absolute() or ".." in pure.parts or not pure.parts:
        raise SessionError(f"output {relative!r} is not a path inside the session {session}")
    resolved = (root / pure).resolve()
    if root not in resolved.parents:
        raise SessionError(f"refusing to write {relative} of {session}: it resolves to {resolved}, outside the "
                           f"session (is {pure.parts[0]}/ a link?); replace the link by a folder")
    return resolved


def session_folder(session: Path | str, relative: str) -> Path:
    """A folder inside ``session`` (e.g. ``derived/eval``), checked like ``session_target`` and created."""
    resolved = _resolve_inside(session, relative)
    reason = _owned_reason(Path(session).resolve(), resolved)
    if reason is not None:
        raise SessionError(f"refusing to write into {relative}: it is {reason} of {session}")
    _make_folder(resolved, SessionError, str(resolved))
    return resolved


def out_target(path: Path | str, option: str = "--out", inputs: Iterable[Path | str] = ()) -> Path:
    """The resolved path of a user-named output file, its parent folder created; ConfigError when it
    names a file a session owns, one of ``inputs`` (the files the command reads), or its folder cannot
    be made."""
    resolved = Path(path).expanduser().resolve()
    for read in inputs:
        if Path(read).expanduser().resolve() == resolved:
            raise ConfigError(f"{option} {path} is {read}, which this command reads: choose another file")
    session = session_of(resolved.parent)
    if session is not None:
        reason = _owned_reason(session, resolved)
        if reason is not None:
            raise ConfigError(f"{option} {path} would overwrite {reason} of {session}: choose another file")
    _make_parent(resolved, ConfigError, option)
    if resolved.is_dir():
        raise ConfigError(f"{option} {path} is a folder; name a file")
    return resolved


def out_folder(path: Path | str, option: str = "--out") -> Path:
    """A user-named output folder, resolved and created; ConfigError when it cannot be, or when it is a
    session folder or a folder of the recording (the files written in it are checked one by one too)."""
    resolved = Path(path).expanduser().resolve()
    session = session_of(resolved)
    if session is not None:
        reason = _owned_reason(session, resolved)
        if reason is not None:
            raise ConfigError(f"{option} {path} is {reason} of {session}: choose another folder")
    _make_folder(resolved, ConfigError, f"{option} folder {path}")
    return resolved


def out_child(folder: Path | str, name: str, option: str = "--out") -> Path:
    """``folder/name`` for a file whose name comes from data (a session id, a stream or label set name),
    checked like ``out_target``: ``name`` must be one plain file name that stays in ``folder`` once
    resolved (SessionError, exit 4, otherwise: the data named it)."""
    return out_target(_child_of(folder, name), option)


def out_child_folder(folder: Path | str, name: str, option: str = "--out") -> Path:
    """Like ``out_child`` for a folder (``out_folder``'s checks), created."""
    return out_folder(_child_of(folder, name), option)


def _child_of(folder: Path | str, name: str) -> Path:
    """``folder/name`` when ``name`` is a single file name that resolves to an entry of ``folder``."""
    plain = (isinstance(name, str) and name not in ("", ".", "..") and "/" not in name and "\\" not in name
             and not any(ord(c) < 32 or ord(c) == 127 for c in name) and len(name.encode("utf-8")) <= 255)
    root = Path(folder).expanduser().resolve()
    if not plain or (root / name).resolve().parent != root:
        raise SessionError(f"refusing to write {shown(name)} in {folder}: a name taken from the data must be one "
                           f"plain file name inside the output folder")
    return root / name


def _make_parent(resolved: Path, error: type[MidasError], option: str = "output") -> None:
    _make_folder(resolved.parent, error, f"the folder of {option} {resolved}")


def _make_folder(folder: Path, error: type[MidasError], what: str) -> None:
    """Create ``folder`` and its parents; ``error`` ("cannot create WHAT: reason") when it cannot be."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise error(f"cannot create {what}: {exc.strerror or exc}") from exc


# ---- atomic writes -----------------------------------------------------------------------------

@contextlib.contextmanager
def replacing(target: Path | str) -> Iterator[Path]:
    """A unique temporary beside ``target`` to write; renamed over ``target`` when the block succeeds,
    removed when it fails. Runs under the lock of the session ``target`` lies in (if any). An OSError
    (disk full, a folder in the way) becomes SessionError for a file in a session, ConfigError elsewhere."""
    target = Path(target)
    session = session_of(target.parent)
    error = SessionError if session is not None else ConfigError
    with session_lock(session) if session is not None else contextlib.nullcontext():
        try:
            tmp = temporary_beside(target)
        except OSError as exc:
            raise error(f"cannot write {target}: {exc.strerror or exc}") from exc
        try:
            yield tmp
            os.replace(tmp, target)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise error(f"cannot write {target}: {exc.strerror or exc}") from exc
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


def temporary_beside(target: Path) -> Path:
    """A new empty file ``.<name>.<random>.tmp`` in ``target``'s folder, with the permissions a file
    created there would get (mkstemp's 0600 would carry over to the result)."""
    fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.fchmod(fd, 0o666 & ~_UMASK)
    os.close(fd)
    return Path(name)


def write_text(target: Path | str, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``target`` via ``replacing``."""
    with replacing(target) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(target)


def write_bytes(target: Path | str, data: bytes) -> Path:
    """Write ``data`` to ``target`` via ``replacing``."""
    with replacing(target) as tmp:
        tmp.write_bytes(data)
    return Path(target)


def write_json(target: Path | str, document: Any) -> Path:
    """Write ``document`` as indented JSON to ``target`` via ``replacing``."""
    return write_text(target, json.dumps(document, indent=2, default=str) + "\n")


# ---- the session lock --------------------------------------------------------------------------

def lock_wait_s() -> float:
    """Seconds a writer waits for another to finish (``MIDAS_LOCK_WAIT_S``, default 600)."""
    raw = os.environ.get(LOCK_WAIT_ENV)
    try:
        return LOCK_WAIT_DEFAULT_S if raw is None else max(0.0, float(raw))
    except ValueError:
        raise ConfigError(f"{LOCK_WAIT_ENV}={raw!r} is not a number of seconds") from None


@contextlib.contextmanager
def session_lock(session: Path | str) -> Iterator[None]:
    """Hold ``session``'s write lock for the block (see the module docstring)."""
    root = Path(session).resolve()
    with _held_guard:
        if root in _held:
            _held[root][1] += 1
            entered = True
        else:
            entered = False
    if entered:
        try:
            yield
        finally:
            with _held_guard:
                _held[root][1] -= 1
        return
    fd = _acquire(root)
    with _held_guard:
        _held[root] = [fd, 1]
    try:
        yield
    finally:
        with _held_guard:
            del _held[root]
        os.close(fd)  # releases the flock


@contextlib.contextmanager
def session_read_lock(session: Path | str) -> Iterator[None]:
    """Hold ``session``'s lock shared for the block, so a reader never sees a writer's files half
    replaced (it waits like a writer). Nothing to hold when no midas ever wrote the session, when the
    lock file cannot be opened (a read-only copy), or when this process holds the write lock."""
    root = Path(session).resolve()
    with _held_guard:
        mine = root in _held
    try:
        fd = None if mine else os.open(root / LOCK_NAME, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        fd = None
    if fd is None:
        yield
        return
    try:
        _wait_for(fd, root, fcntl.LOCK_SH)
        yield
    finally:
        os.close(fd)


def _acquire(root: Path) -> int:
    try:
        fd = os.open(root / LOCK_NAME, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666 & ~_UMASK)
    except OSError as exc:
        raise SessionError(f"cannot lock {root} for writing ({LOCK_NAME}): {exc.strerror or exc}") from exc
    try:
        _wait_for(fd, root, fcntl.LOCK_EX)
    except BaseException:
        os.close(fd)
        raise
    return fd


def _wait_for(fd: int, root: Path, mode: int) -> None:
    """flock ``fd`` in ``mode``, polling up to ``lock_wait_s()`` (one warning when it has to wait)."""
    deadline, said = time.monotonic() + lock_wait_s(), False
    while True:
        try:
            fcntl.flock(fd, mode | fcntl.LOCK_NB)
            return
        except OSError as exc:
            if exc.errno not in (errno.EAGAIN, errno.EACCES):
                raise SessionError(f"cannot lock {root} for writing: {exc.strerror or exc}") from exc
        if time.monotonic() >= deadline:
            raise SessionError(f"{root} is being written by another midas command; gave up waiting after "
                               f"{lock_wait_s():g} s (set {LOCK_WAIT_ENV} to wait longer)")
        if not said:
            log.warning("%s is being written by another midas command; waiting up to %g s for it to finish",
                        root, lock_wait_s())
            said = True
        time.sleep(LOCK_POLL_S)


def is_locked(session: Path | str) -> bool:
    """True while another process holds ``session``'s write lock (this process's own lock: False)."""
    root = Path(session).resolve()
    with _held_guard:
        if root in _held:
            return False
    try:
        fd = os.open(root / LOCK_NAME, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return False
    except OSError:
        return True
    finally:
        os.close(fd)


# ---- provenance ----------------------------------------------------------------------------------

def provenance(command: str, options: dict[str, Any], inputs: dict[str, Any]) -> dict[str, Any]:
    """What a derived file records about the run that made it: a unique ``run_id`` (files written
    together share it; readers compare them), the command and its options, the inputs (file ->
    {sha256, bytes} or whatever identifies them), the midas version, host and UTC time."""
    return {"run_id": uuid.uuid4().hex, "command": command, "options": options, "inputs": inputs,
            "midas_version": __version__, "host": socket.gethostname(),
            "written_utc": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")}
