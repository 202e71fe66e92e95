"""Creating and writing a session folder (format v1, DESIGN.md section 5).

The manifest is written when recording starts (status "recording") and replaced atomically when it
stops. Stream files are append-only CSV, written in whole lines and flushed to the OS after every
batch, so a killed recorder leaves at most a torn last line (see ``repair``).
"""

from __future__ import annotations

import getpass
import os
import platform
import re
import shutil
import socket
import sys
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable

from midas_cli import __version__
from midas_cli.clock import HostClock
from midas_cli.errors import ConfigError, SessionError
from midas_cli.session import stop_facts
from midas_cli.session.columnar import add_binary_copies
from midas_cli.session.folder import make_session_folder
from midas_cli.session.manifest import SCHEMA_VERSION, write_manifest
from midas_cli.session.schema import StreamSpec
from midas_cli.session.streamfile import summarize_stream
from midas_cli.session.sync_statement import recorded_statement

SUBFOLDERS = ("streams", "video", "calib", "derived", "logs")
LOG_FILE = "logs/midas.log"
_NAME_OK = re.compile(r"[A-Za-z0-9][A-Za-z0-9.-]{0,63}")  # bounded: the session id they make is too


@dataclass(frozen=True)
class SessionMetadata:
    """Who did what: recorded in the manifest and encoded in the folder name."""

    subject: str
    task: str
    trial: int
    platform: str = "simulated"
    operator_note: str = ""
    master_rate_hz: float = 30.0

    def __post_init__(self) -> None:
        for key in ("subject", "task", "platform"):
            value = getattr(self, key)
            if not _NAME_OK.fullmatch(value):
                raise ConfigError(f"{key} {value!r} must be up to 64 letters, digits, '.' or '-' (it names the folder)")
        if self.trial < 0:
            raise ConfigError(f"trial must be >= 0, got {self.trial}")
        if not 0 < self.master_rate_hz <= 1000:
            raise ConfigError(f"master rate must be in (0, 1000] Hz, got {self.master_rate_hz}")

    def folder_stem(self) -> str:
        return f"{self.task}_S{self.subject}_T{self.trial}"


def utc_iso(host_ns: int) -> str:
    return datetime.fromtimestamp(host_ns / 1e9, tz=timezone.utc).isoformat(timespec="milliseconds")


class StreamAppender:
    """Appends whole CSV lines to one stream file, unbuffered (each append survives a process kill).

    Used by ``SessionWriter`` and, while recording, by each device worker on the files the recorder
    created: ``create=False`` opens an existing file only (O_WRONLY|O_APPEND, never O_CREAT), so a
    missing file raises FileNotFoundError instead of writing somewhere unexpected."""

    def __init__(self, path: Path, create: bool = False) -> None:
        self.path = Path(path)
        flags = os.O_WRONLY | os.O_APPEND | (os.O_CREAT if create else 0)
        self.fd = os.open(self.path, flags, 0o644)
        self.size = os.fstat(self.fd).st_size  # bytes in the file, always a whole number of lines

    def append(self, text: str) -> int:
        """Hand whole lines to the OS; return the bytes written.

        If the OS refuses part of it (disk full, file too large) the file is cut back to its last
        whole line and the OSError is raised, so a stream never holds a torn line."""
        data = text.encode("utf-8")
        view = memoryview(data)
        try:
            while view:
                view = view[os.write(self.fd, view):]
        except OSError:
            os.ftruncate(self.fd, self.size)
            raise
        self.size += len(data)
        return len(data)

    def sync(self) -> None:
        """fsync the file (flushes the inode's pages, whichever process's fd wrote them)."""
        os.fsync(self.fd)

    def close(self) -> None:
        os.close(self.fd)


class SessionWriter:
    """Owns one session folder while it is recorded."""

    def __init__(self, folder: Path, manifest: dict[str, Any], specs: Iterable[StreamSpec]) -> None:
        self.folder = folder
        self.manifest = manifest
        self.specs = {spec.name: spec for spec in specs}
        self._appenders: dict[str, StreamAppender] = {}
        self.bytes_written = 0
        for spec in self.specs.values():
            self._appenders[spec.name] = StreamAppender(folder / spec.file, create=True)
            self.append(spec.name, spec.header_line())

    @classmethod
    def create(
        cls,
        out_root: Path,
        metadata: SessionMetadata,
        clock: HostClock,
        devices: dict[str, dict[str, Any]],
        specs: list[StreamSpec],
        rig: dict[str, Any] | None = None,
        start_ns: int | None = None,
        extra: dict[str, Any] | None = None,
    ) -> "SessionWriter":
        """Create the folder and write the "recording" manifest. ``start_ns`` (host clock) is given by
        offline writers (simulate, import) whose data carry their own times; live recording uses now.
        ``extra``: further top-level manifest keys (live recording: ``lsl_out``)."""
        start_ns = clock.now_ns() if start_ns is None else start_ns
        manifest = {
            "schema_version": SCHEMA_VERSION,
            "session_id": None,  # the folder's name, once it has one
            "status": "recording",
            "stop_reason": None,
            "metadata": asdict(metadata),
            "rig": rig or {},
            "clock": {"kind": "CLOCK_MONOTONIC anchored to Unix epoch", "anchor_ns": clock.anchor_ns},
            "start": {"utc": utc_iso(start_ns), "host_ns": start_ns},
            "stop": None,
            "software": software_info(),
            "devices": devices,
            "streams": {spec.name: spec.to_manifest() for spec in specs},
            "files": {"log": LOG_FILE},
            **(extra or {}),
        }

        def populate(folder: Path, name: str) -> None:
            manifest["session_id"] = name
            write_manifest(folder, manifest)
            for sub in SUBFOLDERS:
                (folder / sub).mkdir(exist_ok=True)
            stop_facts.reserve(folder)  # room for how it ended, should the disk be full by then

        try:  # the folder appears with its manifest (a kill leaves a session `repair` understands) or not at all
            folder = make_session_folder(out_root, metadata.folder_stem(), start_ns, populate)
        except OSError as exc:  # disk full, quota, permissions: nothing was recorded, nothing is left behind
            raise SessionError(f"cannot create the session in {out_root}: {exc.strerror or exc}") from exc
        try:
            return cls(folder, manifest, specs)
        except OSError as exc:
            shutil.rmtree(folder, ignore_errors=True)
            raise SessionError(f"cannot create the session in {out_root}: {exc.strerror or exc}") from exc

    def append(self, stream: str, text: str) -> None:
        """Append whole CSV lines to a stream and hand them to the OS (survives a process kill).

        Unbuffered: if the OS refuses part of it (disk full, file too large) the file is cut back to
        its last whole line and the OSError is raised, so a stream never holds a torn line."""
        self.bytes_written += self._appenders[stream].append(text)

    def sync(self) -> None:
        """fsync every stream file (survives power loss); called about once a second. While
        recording, the workers append through their own fds; this flushes their pages too."""
        for appender in self._appenders.values():
            appender.sync()

    def sync_stream(self, stream: str) -> None:
        """fsync one stream file (an operator's marker is on disk before it is acknowledged)."""
        self._appenders[stream].sync()

    def finalize(self, status: str, stop_reason: str, stop_ns: int, extra: dict[str, dict[str, Any]]) -> dict:
        """Close the files, describe each from what is on disk, and replace the manifest atomically.

        ``extra`` maps stream name -> recorder facts (dropped, corrupt, latency, outages). When the
        manifest cannot be written (disk full) the stop facts go to the space reserved for them
        (``stop_facts``) for `midas session repair`, and the OSError is raised.
        """
        self.sync()
        for appender in self._appenders.values():
            appender.close()
        for name, spec in self.specs.items():
            entry = self.manifest["streams"][name]
            entry.update(summarize_stream(self.folder / spec.file, spec).manifest_fields())
            entry.update(extra.get(name, {}))
        self.manifest.update(status=status, stop_reason=stop_reason, stop={"utc": utc_iso(stop_ns), "host_ns": stop_ns})
        self.manifest["sync"] = recorded_statement(self.manifest)  # how the streams were synchronised
        try:
            write_manifest(self.folder, self.manifest)  # finished first: the binary copies are an extra
        except OSError:  # the disk is full: `repair` will need to know how it ended
            stop_facts.keep(self.folder, status, stop_reason, extra)
            raise
        stop_facts.release(self.folder)
        add_binary_copies(self.folder, self.manifest)
        write_manifest(self.folder, self.manifest)
        return self.manifest


def software_info() -> dict[str, str]:
    return {
        "name": "midas",
        "version": __version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "host": socket.gethostname(),
        "user": _user(),
    }


def _user() -> str:
    try:
        return getpass.getuser()
    except Exception:  # no passwd entry in some containers
        return ""
