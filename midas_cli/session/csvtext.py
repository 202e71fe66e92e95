"""Text fields in a stream CSV: how a ``text`` column's value is written and how a line is split.

A text value is always written inside double quotes, a quote inside it doubled (RFC 4180): ``"a ""b"", c"``
is ``a "b", c``. A missing value is an empty field (no quotes), so an empty string is never data (the
writer writes it as missing). Control characters (newline, carriage return, tab, escape, ...) are not
allowed in a text value: every data line of a stream is exactly one row, which is what torn-tail repair,
line numbers in errors and the field counts rely on. Bytes inside quotes are UTF-8.

Numeric streams never hold a quote; for them the quote-aware counts below equal plain comma counts.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numpy is imported where it is used: the schema (and `midas session info`) need none
    import numpy as np

_QUOTE, _COMMA, _NEWLINE = ord('"'), ord(","), ord("\n")
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")
TEXT_FIELD = re.compile(rb'"(?:[^"\x00-\x1f\x7f]|"")*"')
_FIELD = re.compile(rb'"(?:[^"]|"")*"|[^,]*')


def control_characters(value: str) -> list[str]:
    """The control characters in ``value`` (as ``repr`` text), which a text column cannot hold."""
    return sorted({repr(c) for c in _CONTROL.findall(value)})


def quote_text(value: object) -> str:
    """One text field: ``value`` quoted (inner quotes doubled); None or "" -> an empty field (missing).
    ValueError if it holds a control character."""
    if value is None or value == "" or (isinstance(value, float) and value != value):
        return ""
    text = str(value)
    bad = control_characters(text)
    if bad:
        raise ValueError(f"text {text[:40]!r} holds control characters {', '.join(bad)}; a text field is one line")
    return '"' + text.replace('"', '""') + '"'


def unquote_text(field: bytes) -> str:
    """A text field's value (``field`` must match ``TEXT_FIELD``; UnicodeDecodeError if not UTF-8)."""
    return field[1:-1].replace(b'""', b'"').decode("utf-8")


def split_fields(line: bytes) -> list[bytes]:
    """The fields of one data line (no newline): split at commas outside quotes. A field that does not
    match the text grammar comes back as it stands (the caller judges it)."""
    fields, pos = [], 0
    while True:
        match = _FIELD.match(line, pos)
        end = match.end() if match else pos
        while end < len(line) and line[end] != _COMMA:  # junk after a closing quote stays in the field
            end += 1
        fields.append(line[pos:end])
        if end >= len(line):
            return fields
        pos = end + 1


def separator_mask(raw: np.ndarray) -> np.ndarray:
    """For the bytes ``raw`` (uint8) of whole lines: True at each comma that separates fields, i.e. one
    with an even number of quotes before it on its line."""
    import numpy as np

    commas = raw == _COMMA
    quotes = raw == _QUOTE
    if not quotes.any():
        return commas
    seen = np.cumsum(quotes, dtype=np.int64)
    at_line_start = np.maximum.accumulate(np.where(raw == _NEWLINE, seen, 0))
    return commas & ((seen - at_line_start) % 2 == 0)


def separators_per_line(separators: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Per line (each ending at one of ``ends``), how many of the bool ``separators`` it holds: summed per
    line (a cumulative sum over the whole file would make an int64 array eight times the file's size)."""
    import numpy as np

    if not len(ends):
        return np.zeros(0, dtype=np.int64)
    starts = np.concatenate(([0], ends[:-1] + 1))
    counts = np.add.reduceat(separators, starts, dtype=np.int64)
    counts[starts == ends] = 0  # an empty line: reduceat gives the element at its start, not 0
    return counts


def count_separators(line: bytes) -> int:
    """Field separators in one line (commas outside quotes)."""
    return sum(part.count(b",") for part in line.split(b'"')[::2])
