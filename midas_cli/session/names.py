"""The one rule for strings that become file names: device, stream, label set names and session ids.

A session folder may come from anyone, and its manifest's strings name files (``streams/<stream>.csv``,
``<out>/<session_id>.mcap``, ``predictions/<session_id>.csv``), so each kind of name has a pattern
that can only ever be one plain file name: no ``/``, ``\\``, NUL or control characters, never ``.`` or
``..`` (the first character is a letter or digit), and bounded in length. The patterns are what midas
itself writes:

* device: a letter, then up to 31 letters, digits, ``_`` or ``-`` (rig files, ``--device NAME=URL``);
* stream: the same, up to 64 characters (a device's name plus a suffix such as ``_marker``);
* session id: a letter or digit, then up to 199 letters, digits, ``.``, ``_`` or ``-``
  (``<task>_S<subject>_T<trial>_<UTC stamp>``);
* label set: a letter or digit, then up to 63 letters, digits, ``.``, ``_`` or ``-``.
"""

from __future__ import annotations

import json
import re
from typing import Any

from midas_cli.errors import MidasError, SessionError

NAME_RULES = {
    "device": (re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,31}"),
               "a letter followed by up to 31 letters, digits, '_' or '-'"),
    "stream": (re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,63}"),
               "a letter followed by up to 63 letters, digits, '_' or '-'"),
    "session id": (re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,199}"),
                   "a letter or digit followed by up to 199 letters, digits, '.', '_' or '-'"),
    "label set": (re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}"),
                  "a letter or digit followed by up to 63 letters, digits, '.', '_' or '-'"),
}
SHOWN_CHARS = 60  # of a refused value, in the message (JSON-escaped: a newline cannot split the line)


def is_name(value: Any, kind: str) -> bool:
    """True when ``value`` is a string that is a valid ``kind`` name (see ``NAME_RULES``)."""
    pattern, _ = NAME_RULES[kind]
    return isinstance(value, str) and pattern.fullmatch(value) is not None


def shown(value: Any) -> str:
    """``value`` for a one-line message: JSON-escaped (newlines, NUL, control characters) and cut short."""
    text = json.dumps(value, ensure_ascii=True)
    return text if len(text) <= SHOWN_CHARS else text[:SHOWN_CHARS] + "...\""


def check_name(value: Any, kind: str, where: str, error: type[MidasError] = SessionError) -> str:
    """``value`` if it is a valid ``kind`` name; else ``error`` saying ``where`` it was found (it names
    files, so nothing else is accepted)."""
    if not is_name(value, kind):
        raise error(f"{where} is {shown(value)}: a {kind} must be {NAME_RULES[kind][1]} (it names files)")
    return value
