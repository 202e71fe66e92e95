"""``logs/stop-facts.json``: how a recording ended, kept for when the final manifest cannot be written.

A full disk that stops a recording (a row read but not written: ``dropped``) usually leaves no room
for the final manifest either, and `midas session repair` then knew only that the recorder "stopped
without finalising". So the writer reserves the space when the session is created (``RESERVED_BYTES``
of spaces, written while there is room) and, if the final manifest cannot be written, overwrites the
reserve in place (no new blocks needed) with the stop facts: status, stop reason and each
stream's recorder counts (dropped, corrupt). `repair` reads them back into the manifest and removes
the file; a finalised session has none (removed once its manifest is in place).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

STOP_FACTS = "logs/stop-facts.json"
RESERVED_BYTES = 16 << 10
COUNTS = ("dropped", "corrupt")  # the per-stream recorder counts kept (the files cannot tell them)


def reserve(folder: Path) -> None:
    """Write the reserve (``RESERVED_BYTES`` spaces); OSError when there is no room for it."""
    path = Path(folder) / STOP_FACTS
    path.parent.mkdir(exist_ok=True)
    path.write_bytes(b" " * RESERVED_BYTES)


def release(folder: Path) -> None:
    """Remove the reserve (the final manifest is in place)."""
    (Path(folder) / STOP_FACTS).unlink(missing_ok=True)


def keep(folder: Path, status: str, stop_reason: str, streams: dict[str, dict[str, Any]]) -> bool:
    """Overwrite the reserve in place with the stop facts (``streams``: name -> recorder facts, of
    which ``COUNTS`` are kept); False (logged) when there is no reserve or it cannot be written."""
    facts = {"status": status, "stop_reason": stop_reason,
             "streams": {name: {k: int(extra[k]) for k in COUNTS if isinstance(extra.get(k), int)}
                         for name, extra in streams.items()}}
    text = json.dumps(facts).encode("utf-8")
    path = Path(folder) / STOP_FACTS
    try:
        if len(text) > RESERVED_BYTES or path.stat().st_size < RESERVED_BYTES:
            raise OSError(f"{len(text)} bytes of stop facts do not fit the reserve")
        with open(path, "r+b") as fh:  # in place: the blocks are allocated already
            fh.write(text.ljust(RESERVED_BYTES))
            fh.flush()
            os.fsync(fh.fileno())
    except OSError as exc:
        log.error("could not keep the stop facts in %s: %s", path, exc)
        return False
    return True


def read(folder: Path) -> dict[str, Any] | None:
    """The stop facts kept by ``keep``, checked (status and stop_reason strings, counts non-negative
    integers); None when there are none (a reserve never written, a kill) or they are malformed."""
    try:
        facts = json.loads((Path(folder) / STOP_FACTS).read_bytes() or b"null")
    except (OSError, ValueError):
        return None
    if not (isinstance(facts, dict) and isinstance(facts.get("status"), str)
            and isinstance(facts.get("stop_reason"), str) and isinstance(facts.get("streams"), dict)):
        return None
    streams = {name: {k: v for k, v in counts.items() if k in COUNTS and type(v) is int and v >= 0}
               for name, counts in facts["streams"].items() if isinstance(counts, dict)}
    return {"status": facts["status"], "stop_reason": facts["stop_reason"], "streams": streams}
