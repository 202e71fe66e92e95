"""Reading a session folder: the only code (with writer/repair) that knows the v1 layout."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

from midas_cli.errors import SessionError
from midas_cli.session.folder import STAGING_DIR
from midas_cli.session.manifest import MANIFEST_NAME, check_inside, load_manifest
from midas_cli.session.schema import StreamSpec

log = logging.getLogger(__name__)
TIME_MARGIN_S = 60  # how far before its start / after its stop a sample's host time may be (at least)
CHUNK_BYTES = 8 << 20  # iter_stream's pieces: about this much CSV text at a time
_TORN_WARNED: set[tuple[Path, int]] = set()  # (file, size): each torn file is reported once per process

if TYPE_CHECKING:  # pandas is imported where it is used: `midas align` reads binary copies without it
    import numpy as np
    import pandas as pd

    from midas_cli.session.values import ParsedStream

# numpy (and pandas) come in with columnar/values, imported where a stream's rows are read: opening a
# session and its manifest (`midas session info|list`) needs neither.


@dataclass
class Session:
    """An opened session folder with a validated manifest."""

    path: Path
    manifest: dict[str, Any]

    @classmethod
    def open(cls, path: Path | str, allow_failed: bool = False) -> "Session":
        """Open a session folder. A recording that failed to start (status 'failed') holds no data and
        is refused unless ``allow_failed`` (for `session info|list|verify`, which describe it)."""
        folder = Path(path)
        if not folder.is_dir():
            raise SessionError(f"{folder} is not a folder")
        session = cls(folder, load_manifest(folder))
        if session.status == "failed" and not allow_failed:
            reason = " ".join(str(session.manifest.get("stop_reason") or "no reason recorded").split())
            raise SessionError(f"{folder} is a recording that failed to start ({reason}); it holds no data")
        return session

    @property
    def status(self) -> str:
        return self.manifest["status"]

    @property
    def metadata(self) -> dict[str, Any]:
        return self.manifest["metadata"]

    @property
    def stream_names(self) -> list[str]:
        return list(self.manifest["streams"])

    def stream_spec(self, name: str) -> StreamSpec:
        return StreamSpec.from_manifest(name, self._stream_entry(name))

    def stream_path(self, name: str) -> Path:
        return check_inside(self.path, self._stream_entry(name)["file"])

    def duration_s(self) -> float | None:
        stop = self.manifest.get("stop") or {}
        if "host_ns" not in stop:
            return None
        return (stop["host_ns"] - self.manifest["start"]["host_ns"]) / 1e9

    def plausible_host_ns(self) -> tuple[int, int | None]:
        """The host times (Unix-epoch ns) a sample of this session can have: from its start to its stop
        (None while it has none), each widened by ``TIME_MARGIN_S`` or the session's length, whichever
        is longer. A ``t_host_ns`` outside is damage (`verify` names it; `replay` refuses it)."""
        start = self.manifest["start"]["host_ns"]
        stop = (self.manifest.get("stop") or {}).get("host_ns")
        margin = max(TIME_MARGIN_S * 10**9, 0 if stop is None else stop - start)
        return start - margin, None if stop is None else stop + margin

    def read_stream(self, name: str, allow_incomplete: bool = False) -> pd.DataFrame:
        """One stream as a DataFrame: int columns as int64 (exact ns times), floats with NaN = missing.
        Every value is checked against its column (SessionError naming file and line); a torn last
        line is left out, with a warning."""
        self._refuse_unfinished(allow_incomplete)
        return self._parse_csv(name).frame

    def read_columns(self, name: str, allow_incomplete: bool = False) -> np.ndarray:
        """One stream as a structured array (one field per column, ints int64, floats float64 with NaN =
        missing): its binary copy memory-mapped when that still matches the CSV, else the CSV parsed
        (as ``read_stream`` does)."""
        self._refuse_unfinished(allow_incomplete)
        from midas_cli.session.columnar import load_binary_copy
        from midas_cli.session.values import structured

        table = load_binary_copy(self.path, name, self._stream_entry(name))
        return structured(self._parse_csv(name).frame, self.stream_spec(name)) if table is None else table

    def iter_stream(self, name: str, chunk_bytes: int = CHUNK_BYTES,
                    allow_incomplete: bool = False) -> Iterator[pd.DataFrame]:
        """One stream in pieces of whole lines (about ``chunk_bytes`` of CSV each), each parsed and checked as
        ``read_stream`` does (same columns and dtypes), so memory stays flat in the stream's length. At least
        one frame comes (empty for a stream without rows). A bad value anywhere refuses the stream with the
        error ``read_stream`` gives (the file is then parsed whole once, to name the line); a torn last line
        is left out, with a warning."""
        self._refuse_unfinished(allow_incomplete)
        from midas_cli.session.values import ParsedStream, open_regular, parse_stream_bytes, parse_stream_file

        path, spec = self.stream_path(name), self.stream_spec(name)
        with open_regular(path) as fh:
            header = fh.readline(len(spec.header_line()) + 1)
            rows, tail, sent = 0, b"", False
            while True:
                block = fh.read(max(int(chunk_bytes), 1))
                data = tail + block
                cut = data.rfind(b"\n") + 1 if block else 0
                body, tail = data[:cut], data[cut:]
                if body or not (block or sent):
                    try:
                        frame = parse_stream_bytes(header + body, spec, path).frame
                    except SessionError as exc:
                        parse_stream_file(path, spec)  # raises the error naming the file's own line number
                        raise exc  # (only if the whole file parses: cannot happen, kept for safety)
                    rows += len(frame)
                    sent = True
                    yield frame
                if not block:
                    break
        if tail:
            _warn_torn_tail(path, ParsedStream(frame.iloc[:0], len(tail)), rows)

    def _parse_csv(self, name: str) -> ParsedStream:
        from midas_cli.session.values import parse_stream_file

        path = self.stream_path(name)
        parsed = parse_stream_file(path, self.stream_spec(name))
        if parsed.torn_tail_bytes:
            _warn_torn_tail(path, parsed)
        return parsed

    def _refuse_unfinished(self, allow_incomplete: bool) -> None:
        if self.status == "recording" and not allow_incomplete:
            raise SessionError(
                f"{self.path} is still marked 'recording' (crashed or running): run `midas session repair {self.path}`"
            )

    def _stream_entry(self, name: str) -> dict[str, Any]:
        try:
            return self.manifest["streams"][name]
        except KeyError:
            known = ", ".join(self.stream_names) or "none"
            raise SessionError(f"session {self.path} has no stream {name!r} (streams: {known})") from None


def _warn_torn_tail(path: Path, parsed: ParsedStream, rows: int | None = None) -> None:
    key = (path, parsed.torn_tail_bytes)
    if key in _TORN_WARNED:
        return
    _TORN_WARNED.add(key)
    log.warning("%s ends in a torn line (%d bytes without a newline: the recorder stopped mid-write); using "
                "its %d whole lines", path, parsed.torn_tail_bytes, len(parsed.frame) if rows is None else rows)


def find_sessions(root: Path | str, max_depth: int = 3) -> Iterator[Path]:
    """Session folders (holding a manifest.json) under ``root``, sorted, at most ``max_depth`` deep."""
    root = Path(root)
    if not root.is_dir():
        raise SessionError(f"{root} is not a folder")
    if (root / MANIFEST_NAME).is_file():
        yield root
        return
    yield from _walk(root, max_depth)


def _walk(folder: Path, depth: int) -> Iterator[Path]:
    if depth <= 0:
        return
    children = (p for p in folder.iterdir() if p.name != STAGING_DIR)  # sessions being made
    for child in sorted(p for p in children if p.is_dir() and not p.is_symlink()):
        if (child / MANIFEST_NAME).is_file():
            yield child
        else:
            yield from _walk(child, depth - 1)
