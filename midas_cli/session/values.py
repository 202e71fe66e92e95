"""Strict parsing of a stream CSV: every value checked against its column's declared type and range.

A stream file is a header line (the manifest's column names) and whole data lines, each with one
field per column: ``int`` columns hold decimal integers that fit int64, ``float`` columns hold finite
decimal numbers; an empty field is a missing value (allowed everywhere but ``seq`` and ``t_host_ns``).
Nothing else is data: no ``nan``/``inf`` text (the writer writes missing values as empty fields), no
spaces, quotes or bytes that are not ASCII. Ranges: a float's magnitude is at most ``FLOAT_LIMIT``
(no device midas records measures anything near it: 1e308 is damage), a column with unit ``bool`` holds
0 or 1. A torn last line (no newline: a killed recorder) is not data either: it is left out and its
size reported, so readers can use the whole lines and say so. Anything else refuses the file with a
SessionError naming the file and line. A ``text`` column's fields are quoted UTF-8 text without control
characters (``csvtext.py``); a stream with text columns (an event stream: few rows) is checked line by
line, its number columns as strictly as anywhere else.

The checks are vectorised (one byte-class pass, one pandas parse, one pass per column); only when
the parse fails is the file parsed again as text to find the first bad value.
"""

from __future__ import annotations

import io
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from midas_cli.errors import SessionError
from midas_cli.session.csvtext import TEXT_FIELD, separator_mask, separators_per_line, split_fields, unquote_text
from midas_cli.session.schema import Column, StreamSpec

if TYPE_CHECKING:
    import pandas as pd

FLOAT_LIMIT = 1e15
REQUIRED = ("seq", "t_host_ns")  # never missing
UNIT_RANGES = {"bool": (0, 1)}
_ALLOWED = np.zeros(256, dtype=bool)
_ALLOWED[np.frombuffer(b"0123456789+-.eE,\n", dtype=np.uint8)] = True
REMEDY = "the file is damaged: restore it from a copy, or re-record (`midas session verify` lists every problem)"


@dataclass
class ParsedStream:
    """A stream file's whole lines parsed: ``frame`` columns as the spec's (int64 for seq/t_host_ns,
    nullable Int64 for other int columns, float64 with NaN = missing); ``torn_tail_bytes`` bytes after
    the last newline were left out."""

    frame: "pd.DataFrame"
    torn_tail_bytes: int


def open_regular(path: Path):
    """``path`` opened for reading in binary; SessionError if it is not a regular file (a FIFO, device or
    folder is refused without being opened for a blocking read) or cannot be opened."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
        if stat.S_ISREG(mode):
            fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO swapped in after the stat cannot block
            try:
                mode = os.fstat(fd).st_mode
                if stat.S_ISREG(mode):
                    os.set_blocking(fd, True)
                    return os.fdopen(fd, "rb")
            except BaseException:
                os.close(fd)
                raise
            os.close(fd)
    except OSError as exc:
        raise SessionError(f"cannot read {path}: {exc.strerror or exc}") from exc
    raise SessionError(f"{path} is not a regular file ({_kind(mode)}); expected the stream's CSV file: "
                       f"put the recorded file back in its place")


def read_regular_file(path: Path) -> bytes:
    """The bytes of ``path`` (see ``open_regular``)."""
    with open_regular(path) as fh:
        try:
            return fh.read()
        except OSError as exc:
            raise SessionError(f"cannot read {path}: {exc.strerror or exc}") from exc


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISDIR, "a folder"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a plain file"


def parse_stream_file(path: Path, spec: StreamSpec) -> ParsedStream:
    """Read and strictly parse ``path`` (see the module docstring)."""
    return parse_stream_bytes(read_regular_file(path), spec, Path(path))


def parse_stream_bytes(data: bytes, spec: StreamSpec, path: Path) -> ParsedStream:
    """Strictly parse the bytes of a stream file (``path`` names it in errors)."""
    header_end = data.find(b"\n")
    if header_end < 0:
        raise SessionError(f"{path}: no header line ({len(data)} bytes without a newline); expected "
                           f"{spec.header_line().strip()!r}; {REMEDY}")
    header = data[: header_end + 1].decode("utf-8", "replace")
    if header != spec.header_line():
        raise SessionError(f"{path} line 1: header {_short(header.strip())!r} does not match the manifest's columns "
                           f"{_short(spec.header_line().strip())!r}; {REMEDY}")
    body_end = data.rfind(b"\n") + 1
    body = data[header_end + 1 : body_end]
    if spec.has_text:
        _check_text_lines(body, spec, path)
    else:
        _check_bytes(body, spec, path)
    _check_widths(body, spec, path)
    frame = _parse(body, spec, path)
    _check_ranges(frame, spec, path)
    return ParsedStream(frame, len(data) - body_end)


def _check_bytes(body: bytes, spec: StreamSpec, path: Path) -> None:
    raw = np.frombuffer(body, dtype=np.uint8)
    bad = np.flatnonzero(~_ALLOWED[raw])
    if not len(bad):
        return
    pos = int(bad[0])
    line, column, text = _locate(body, pos, spec)
    byte = body[pos]
    what = (f"byte 0x{byte:02x}, which is not ASCII text (the file is not the UTF-8 CSV midas writes)" if byte >= 0x80
            else f"{_short(text)!r}, which is not a number")
    raise SessionError(f"{path} line {line}, column {column!r}: {what}; expected {_expected(spec, column)}; {REMEDY}")


def _check_text_lines(body: bytes, spec: StreamSpec, path: Path) -> None:
    """Every field of every line: text columns quoted UTF-8 text (or empty), the others only the bytes a
    number can hold (their values are checked by the parse that follows)."""
    for number, line in enumerate(body.split(b"\n")[:-1], start=2):
        fields = split_fields(line)
        if len(fields) != len(spec.columns):
            raise SessionError(f"{path} line {number}: {len(fields)} fields, expected {len(spec.columns)} "
                               f"(damage inside the file, not a torn last line); {REMEDY}")
        for column, field in zip(spec.columns, fields):
            if column.dtype == "text" and field and not _is_text(field):
                raise SessionError(f"{path} line {number}, column {column.name!r}: {_short(_shown(field))!r}; "
                                   f"expected {_expected(spec, column.name)}; {REMEDY}")
            if column.dtype != "text" and not _ALLOWED[np.frombuffer(field, dtype=np.uint8)].all():
                raise SessionError(f"{path} line {number}, column {column.name!r}: {_short(_shown(field))!r}, which "
                                   f"is not a number; expected {_expected(spec, column.name)}; {REMEDY}")


def _is_text(field: bytes) -> bool:
    if not TEXT_FIELD.fullmatch(field):
        return False
    try:
        unquote_text(field)
    except UnicodeDecodeError:
        return False
    return True


def _shown(field: bytes) -> str:
    return field.decode("utf-8", "replace")


def _check_widths(body: bytes, spec: StreamSpec, path: Path) -> None:
    if not body:
        return
    width = len(spec.columns)
    raw = np.frombuffer(body, dtype=np.uint8)
    ends = np.flatnonzero(raw == ord("\n"))
    per_line = separators_per_line(separator_mask(raw), ends) + 1
    wrong = np.flatnonzero(per_line != width)
    if len(wrong):
        first = int(wrong[0])
        raise SessionError(f"{path} line {first + 2}: {per_line[first]} fields, expected {width} "
                           f"({len(wrong)} line(s) like it: damage inside the file, not a torn last line); {REMEDY}")


def _dtypes(spec: StreamSpec) -> dict[str, str]:
    kinds = {"int": "Int64", "float": "float64", "text": "object"}
    return {c.name: "int64" if c.name in REQUIRED and c.dtype == "int" else kinds[c.dtype] for c in spec.columns}


def _parse(body: bytes, spec: StreamSpec, path: Path) -> "pd.DataFrame":
    import pandas as pd

    if not body:
        return pd.DataFrame({name: pd.Series([], dtype=dtype) for name, dtype in _dtypes(spec).items()})
    try:
        return pd.read_csv(io.BytesIO(body), header=None, names=spec.column_names, dtype=_dtypes(spec),
                           engine="c", keep_default_na=False, na_values=[""])
    except (ValueError, TypeError, OverflowError) as exc:  # ParserError is a ValueError
        raise _first_bad_value(body, spec, path, exc) from exc


def _first_bad_value(body: bytes, spec: StreamSpec, path: Path, exc: Exception) -> SessionError:
    """The error for the first value that is not of its column's type (the slow path: text parse)."""
    import pandas as pd

    text = pd.read_csv(io.BytesIO(body), header=None, names=spec.column_names, dtype=str, engine="c",
                       keep_default_na=False)
    first: tuple[int, int] | None = None
    for k, column in enumerate(spec.columns):
        bad = np.flatnonzero(~_valid_text(text[column.name], column).to_numpy())
        if len(bad) and (first is None or bad[0] < first[0]):
            first = (int(bad[0]), k)
    if first is None:
        return SessionError(f"{path}: cannot parse ({exc}); {REMEDY}")
    row, k = first
    column = spec.columns[k]
    value = text[column.name].iloc[row]
    got = "an empty field" if value == "" else f"{_short(value)!r}"
    return SessionError(f"{path} line {row + 2}, column {column.name!r}: {got}; expected "
                        f"{_expected(spec, column.name)}; {REMEDY}")


def _valid_text(values: "pd.Series", column: Column) -> "pd.Series":
    import pandas as pd

    empty = values == ""
    if column.dtype == "text":
        return pd.Series(True, index=values.index)
    if column.dtype == "int":
        ok = values.str.fullmatch(r"[+-]?[0-9]+")
        long = ok & (values.str.len() > 18)
        if long.any():
            ok[long] = [-(2**63) <= int(v) < 2**63 for v in values[long]]
    else:
        ok = pd.to_numeric(values.where(~empty, "0"), errors="coerce").notna()
    return (ok | empty) if column.name not in REQUIRED else (ok & ~empty)


def _check_ranges(frame: "pd.DataFrame", spec: StreamSpec, path: Path) -> None:
    for column in (c for c in spec.columns if c.dtype != "text"):
        low, high = UNIT_RANGES.get(column.unit, (-FLOAT_LIMIT, FLOAT_LIMIT) if column.dtype == "float" else (None, None))
        if low is None:
            continue
        values = frame[column.name].to_numpy(np.float64, na_value=np.nan)
        bad = np.flatnonzero((values < low) | (values > high) | np.isinf(values))
        if len(bad):
            row = int(bad[0])
            raise SessionError(f"{path} line {row + 2}, column {column.name!r}: {values[row]:g} is out of range; "
                               f"expected {_expected(spec, column.name)}; {REMEDY}")


def _expected(spec: StreamSpec, name: str | None) -> str:
    column = next((c for c in spec.columns if c.name == name), None)
    if column is None:
        return "numbers separated by commas"
    missing = "" if column.name in REQUIRED else " or an empty field (missing)"
    if column.dtype == "text":
        return f"text in double quotes (inner quotes doubled, no control characters){missing}"
    if column.unit in UNIT_RANGES:
        low, high = UNIT_RANGES[column.unit]
        return f"{low} or {high} ({column.unit}){missing}"
    if column.dtype == "int":
        return f"an integer that fits 64 bits{missing}"
    return f"a finite decimal number within +-{FLOAT_LIMIT:.0e}{missing}"


def _locate(body: bytes, pos: int, spec: StreamSpec) -> tuple[int, str | None, str]:
    """(file line number, column name, field text) of byte offset ``pos`` in ``body``."""
    start = body.rfind(b"\n", 0, pos) + 1
    end = body.find(b"\n", pos)
    line_bytes = body[start : end if end >= 0 else len(body)]
    index = body.count(b",", start, pos)
    fields = line_bytes.split(b",")
    name = spec.columns[index].name if index < len(spec.columns) else None
    text = fields[index].decode("utf-8", "replace") if index < len(fields) else ""
    return body.count(b"\n", 0, start) + 2, name, text


def _short(text: str, limit: int = 60) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def structured(frame: "pd.DataFrame", spec: StreamSpec) -> np.ndarray:
    """``frame`` (as parsed) as a structured array: int columns int64, or float64 with NaN where an int
    column has missing values; float columns float64; text columns fixed-width unicode ("" = missing)."""
    fields = {}
    for column in spec.columns:
        series = frame[column.name]
        if column.dtype == "text":
            texts = series.fillna("").astype(str).to_numpy()
            fields[column.name] = texts.astype(f"U{max([1, *map(len, texts)])}")
        elif column.dtype == "int" and not series.hasnans:
            fields[column.name] = series.to_numpy(np.int64)
        else:
            fields[column.name] = series.to_numpy(np.float64, na_value=np.nan)
    table = np.empty(len(frame), dtype=[(name, values.dtype) for name, values in fields.items()])
    for name, values in fields.items():
        table[name] = values
    return table
