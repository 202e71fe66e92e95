"""The pty emulators' send-time log: when each record's last byte went out, on the host's monotonic clock.

The timestamp-error benchmark (benchmarks/bench_timestamp_error.py) compares each recorded row's
``t_host_ns`` with the moment the emulator's ``os.write`` that carried the row's last byte returned.
Off unless an emulator's config names a file (``send_log``): a normal run pays one ``is None`` test
per write.

The file is CSV text. The header names the record's identity columns (the trakSTAR: ``cycle``, its
measurement counter; the pedal board: ``boot,seq``, the board's boot and sample counter), then
``t_due_ns`` (when the device's own clock made the record due) and ``t_out_ns`` (just after the write
of its last byte returned). Both are ``time.monotonic_ns()``, the clock midas stamps rows with:
``t_host_ns = monotonic ns + the session's clock.anchor_ns`` (midas_cli/clock.py, the manifest's
``clock``). One line per record, in the order the records went out.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from midas_cli.errors import ConfigError

TIME_COLUMNS = ("t_due_ns", "t_out_ns")


class SendLog:
    """An open send-time log (buffered; complete once :meth:`close` returns)."""

    def __init__(self, path: str | Path, identity: tuple[str, ...]) -> None:
        self.path = Path(path)
        self.identity = identity
        try:
            self._file = self.path.open("w", encoding="ascii")
        except OSError as exc:
            raise ConfigError(f"cannot write the emulator's send log {self.path}: {exc.strerror}") from exc
        self._file.write(",".join((*identity, *TIME_COLUMNS)) + "\n")

    def record(self, identity: tuple[int, ...], due_s: float, out_ns: int) -> None:
        """One record went out: its identity, when it was due (``time.monotonic()`` seconds) and when
        the write of its last byte returned (``time.monotonic_ns()``)."""
        self._file.write(",".join(map(str, identity)) + f",{round(due_s * 1e9)},{out_ns}\n")

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()


def read_send_log(path: str | Path) -> dict[str, np.ndarray]:
    """A send log as columns (name -> int64 array, in file order); ConfigError if it is not one."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="ascii").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read the emulator's send log {path}: {exc}") from exc
    if not lines or not lines[0].endswith(",".join(TIME_COLUMNS)):
        raise ConfigError(f"{path} is not an emulator send log (header {lines[0][:80] if lines else ''!r})")
    names = lines[0].split(",")
    rows = []
    for number, line in enumerate(lines[1:], start=2):
        fields = line.split(",")
        if len(fields) != len(names) or not all(f.lstrip("-").isdigit() for f in fields):
            raise ConfigError(f"{path}, line {number}: expected {len(names)} integers, got {line[:80]!r}")
        rows.append([int(f) for f in fields])
    table = np.array(rows, dtype=np.int64).reshape(-1, len(names))  # (records, columns)
    return {name: table[:, i] for i, name in enumerate(names)}
