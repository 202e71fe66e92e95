"""Stream schemas: the columns of one per-stream CSV file, their units, frames and clocks.

Every stream starts with the two columns the recorder guarantees:
  * ``seq``       -- the device's own sample counter (or frame index), never rewritten;
  * ``t_host_ns`` -- host clock (Unix-epoch ns, monotonic-anchored) when the bytes were read.
Missing values (a hand the camera did not see, a sensor record that failed framing) are written as
empty fields, never as in-band sentinels such as 0 or -1. A ``text`` column (an event stream's marker
text) holds one line of text, always quoted (``session/csvtext.py``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Sequence

from midas_cli.errors import SessionError
from midas_cli.session.csvtext import quote_text

DTYPES = ("int", "float", "text")


@dataclass(frozen=True)
class Column:
    """One CSV column. ``clock`` is set for time columns: "host" or "device"."""

    name: str
    dtype: str = "float"
    unit: str = ""
    decimals: int = 3
    clock: str | None = None
    frame: str | None = None
    description: str = ""

    def to_manifest(self) -> dict[str, Any]:
        entry = {k: v for k, v in asdict(self).items() if v not in (None, "")}
        if self.dtype != "float":
            entry.pop("decimals", None)
        return entry

    @classmethod
    def from_manifest(cls, entry: dict[str, Any]) -> "Column":
        unknown = set(entry) - {f for f in cls.__dataclass_fields__}
        if unknown or "name" not in entry or entry.get("dtype", "float") not in DTYPES:
            raise SessionError(f"malformed column entry {entry!r} in manifest")
        return cls(**entry)


SEQ = Column("seq", "int", "count", description="device sample counter / frame index")
T_HOST = Column("t_host_ns", "int", "ns", clock="host", description="host clock when the bytes were read")


@dataclass(frozen=True)
class StreamSpec:
    """A stream: its name (file ``streams/<name>.csv``), producing device, columns and nominal rate.

    ``nominal_rate_hz`` is None for an event stream (sync-marker toggles, irregular LSL markers): its
    rows come when something happens, so it has no rate to fall short of and never goes stale.

    ``marker`` names the text column that stands for a row where one value must (an LSL or XDF marker
    stream's one string channel, devices/lsl/outlet.py); "" for the first text column."""

    name: str
    device: str
    columns: tuple[Column, ...]
    nominal_rate_hz: float | None
    description: str = ""
    marker: str = ""
    _formatters: tuple = field(default=(), compare=False, repr=False)

    def __post_init__(self) -> None:
        names = [c.name for c in self.columns]
        if names[:2] != ["seq", "t_host_ns"]:
            raise SessionError(f"stream {self.name!r} must start with seq, t_host_ns columns, got {names[:2]}")
        if len(set(names)) != len(names):
            raise SessionError(f"stream {self.name!r} has duplicate column names")
        if self.nominal_rate_hz is not None and not self.nominal_rate_hz > 0:
            raise SessionError(f"stream {self.name!r}: nominal rate must be positive Hz or None (events), "
                               f"got {self.nominal_rate_hz}")
        if self.marker and self.marker not in [c.name for c in self.columns if c.dtype == "text"]:
            raise SessionError(f"stream {self.name!r}: marker {self.marker!r} is not one of its text columns")
        object.__setattr__(self, "_formatters", tuple(_formatter(c) for c in self.columns))

    @property
    def is_events(self) -> bool:
        """True for an event stream: no nominal rate, rows only when something happens."""
        return self.nominal_rate_hz is None

    @property
    def has_text(self) -> bool:
        """True when a column holds text (parsed line by line, not by the vectorised number checks)."""
        return any(c.dtype == "text" for c in self.columns)

    @property
    def marker_column(self) -> Column | None:
        """The text column that stands for a row (``marker``, else the first text column); None without one."""
        texts = [c for c in self.columns if c.dtype == "text"]
        return next((c for c in texts if c.name == self.marker), texts[0] if texts else None)

    @property
    def file(self) -> str:
        return f"streams/{self.name}.csv"

    @property
    def column_names(self) -> list[str]:
        return [c.name for c in self.columns]

    def header_line(self) -> str:
        return ",".join(self.column_names) + "\n"

    def format_rows(self, rows: Sequence[Sequence[Any]]) -> str:
        """CSV text for ``rows`` (each a sequence with one value per column), newline-terminated."""
        fmts = self._formatters
        width = len(fmts)
        lines = []
        for row in rows:
            if len(row) != width:
                raise SessionError(f"stream {self.name!r}: row has {len(row)} values, expected {width}")
            lines.append(",".join([f(v) for f, v in zip(fmts, row)]))
        return "\n".join(lines) + "\n" if lines else ""

    def to_manifest(self) -> dict[str, Any]:
        entry = {
            "device": self.device,
            "file": self.file,
            "nominal_rate_hz": self.nominal_rate_hz,
            "timing": "events" if self.is_events else "regular",
            "description": self.description,
            "columns": [c.to_manifest() for c in self.columns],
        }
        return {**entry, "marker": self.marker} if self.marker else entry

    @classmethod
    def from_manifest(cls, name: str, entry: dict[str, Any]) -> "StreamSpec":
        try:
            columns = tuple(Column.from_manifest(c) for c in entry["columns"])
            rate, marker = entry["nominal_rate_hz"], entry.get("marker", "")
            if not isinstance(marker, str):
                raise TypeError(f"marker must be a column name, got {marker!r}")
            return cls(name, entry["device"], columns, None if rate is None else float(rate),
                       entry.get("description", ""), marker)
        except (KeyError, TypeError, ValueError) as exc:
            raise SessionError(f"malformed stream {name!r} in manifest: {exc}") from exc


def _formatter(column: Column):
    if column.dtype == "int":
        return _format_int
    if column.dtype == "text":
        return quote_text
    template = "{:.%df}" % column.decimals

    def format_float(value: Any) -> str:
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return ""
        return template.format(value)

    return format_float


def _format_int(value: Any) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return str(int(value))
