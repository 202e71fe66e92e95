"""Files that devices write beside their streams (raw packets, RGB-D video, calibration copies), and
streams added to a finished session by an offline step (``midas extract``).

* Raw packet files ``streams/<name>.raw``: a 16-byte magic line, then one record per packet received,
  ``<qI`` (t_host_ns int64, payload length uint32, little-endian) followed by the payload bytes. The
  decoded stream's ``raw_offset`` column is the byte offset of the packet's record, so every decoded
  row points at the exact bytes it came from. Written unbuffered (a killed recorder loses nothing the
  OS accepted); a torn last record is reported by :func:`read_raw_packets`, not guessed.
* Device files in ``video/`` and ``calib/`` are named by the device; :func:`device_file` checks the
  name stays inside the session folder.
* :func:`add_stream` writes a complete stream file at once (temporary file, rename) and describes it in
  the manifest like a recorded one, with ``derived_by`` saying which step produced it.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Any, Iterator, Sequence

from midas_cli.errors import SessionError
from midas_cli.session.columnar import BINARY_KEY, binary_file, write_binary_copy
from midas_cli.session.manifest import check_inside, load_manifest, write_manifest
from midas_cli.session.outputs import inside_session, replacing, session_lock
from midas_cli.session.schema import StreamSpec
from midas_cli.session.streamfile import summarize_stream

RAW_MAGIC = b"MIDAS-RAW-PKT-1\n"
RAW_RECORD = struct.Struct("<qI")
DEVICE_FOLDERS = ("video", "calib", "streams")


def device_file(session_dir: Path | str, folder: str, filename: str) -> Path:
    """Absolute path of ``folder/filename`` inside the session (folder: video, calib or streams)."""
    if folder not in DEVICE_FOLDERS or "/" in filename or not filename:
        raise SessionError(f"device file {folder}/{filename} is not allowed (folders: {', '.join(DEVICE_FOLDERS)})")
    path = check_inside(Path(session_dir), f"{folder}/{filename}")
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def raw_file_name(stream: str) -> str:
    """Relative path of the raw packet file kept beside ``streams/<stream>.csv``."""
    return f"streams/{stream}.raw"


class RawPacketWriter:
    """Appends packets to a raw packet file (created with its magic if new)."""

    def __init__(self, session_dir: Path | str, stream: str) -> None:
        self.path = device_file(session_dir, "streams", f"{stream}.raw")
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        self.size = os.fstat(self._fd).st_size
        if self.size == 0:
            self._write(RAW_MAGIC)

    def append(self, t_host_ns: int, payload: bytes) -> int:
        """Write one packet; return the byte offset of its record (for the ``raw_offset`` column)."""
        offset = self.size
        self._write(RAW_RECORD.pack(t_host_ns, len(payload)) + payload)
        return offset

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self._fd, view):]
        self.size += len(data)

    def close(self) -> None:
        if self._fd >= 0:
            os.fsync(self._fd)
            os.close(self._fd)
            self._fd = -1


def read_raw_packets(path: Path | str) -> Iterator[tuple[int, int, bytes]]:
    """(offset, t_host_ns, payload) for every record of a raw packet file; SessionError if malformed."""
    data = Path(path).read_bytes()
    if not data.startswith(RAW_MAGIC):
        raise SessionError(f"{path} is not a midas raw packet file (magic {RAW_MAGIC!r} missing)")
    offset = len(RAW_MAGIC)
    while offset < len(data):
        if offset + RAW_RECORD.size > len(data):
            raise SessionError(f"{path}: torn record header at byte {offset}")
        t_host_ns, length = RAW_RECORD.unpack_from(data, offset)
        end = offset + RAW_RECORD.size + length
        if end > len(data):
            raise SessionError(f"{path}: torn record at byte {offset} ({length} payload bytes announced)")
        yield offset, t_host_ns, data[offset + RAW_RECORD.size:end]
        offset = end


def add_stream(session_path: Path | str, spec: StreamSpec, rows: Sequence[Sequence[Any]],
               derived_by: dict[str, Any], replace: bool = False) -> Path:
    """Write ``rows`` as stream ``spec.name`` of a finished session and describe it in the manifest.

    Refuses to replace an existing stream unless ``replace`` (a recorded stream never: only one that an
    earlier offline step added, marked ``derived_by``)."""
    folder = Path(session_path)
    with session_lock(folder):  # the manifest is read, changed and replaced: one writer at a time
        return _add_stream_locked(folder, spec, rows, derived_by, replace)


def _add_stream_locked(folder: Path, spec: StreamSpec, rows: Sequence[Sequence[Any]], derived_by: dict[str, Any],
                       replace: bool) -> Path:
    manifest = load_manifest(folder)
    if manifest["status"] == "recording":
        raise SessionError(f"{folder} is still recording (or crashed): run `midas session repair {folder}` first")
    existing = manifest["streams"].get(spec.name)
    if existing is not None and not (replace and "derived_by" in existing):
        what = "was recorded" if "derived_by" not in existing else "exists (use --force to replace it)"
        raise SessionError(f"{folder}: stream {spec.name!r} {what}; choose another name")
    path = inside_session(folder, spec.file)
    inside_session(folder, binary_file(spec)).unlink(missing_ok=True)  # a copy of what is being replaced
    with replacing(path) as tmp:
        tmp.write_text(spec.header_line() + spec.format_rows(rows), encoding="utf-8")
    entry = {**spec.to_manifest(), **summarize_stream(path, spec).manifest_fields(), "derived_by": derived_by}
    try:
        entry[BINARY_KEY] = write_binary_copy(folder, spec, entry["sha256"])
    except (SessionError, OSError):  # no copy (disk full): readers parse the CSV
        pass
    manifest["streams"][spec.name] = entry
    write_manifest(folder, manifest)
    return path


def last_recorded_seq(session_dir: Path | str, stream: str) -> int | None:
    """``seq`` of the last whole line of ``streams/<stream>.csv`` while it is recorded (None if no rows):
    a device reopened after an outage continues its own counter from there."""
    path = check_inside(Path(session_dir), f"streams/{stream}.csv")
    if not path.is_file():
        return None
    with open(path, "rb") as fh:
        fh.seek(max(0, path.stat().st_size - 65536))
        lines = fh.read().split(b"\n")[:-1]  # the part after the last newline is not a whole line
    for line in reversed(lines):
        first = line.split(b",", 1)[0]
        if first.isdigit():
            return int(first)
    return None
