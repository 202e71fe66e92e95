"""What every device backend provides to the recorder's worker processes.

A backend is opened from a URL (``sim://emht?rate=240``); real, emulated and simulated backends
share this interface and the same worker code path. ``read`` returns rows whose first two values
are ``seq`` (the device's counter) and ``t_host_ns`` (host clock when the bytes were read).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, Callable, TypeVar
from urllib.parse import parse_qsl, urlsplit

from midas_cli.clock import HostClock
from midas_cli.errors import ConfigError
from midas_cli.session.schema import StreamSpec

KINDS = ("emht", "fps", "video", "handkp", "raven", "lsl")
T = TypeVar("T")


@dataclass(frozen=True)
class DeviceUrl:
    """A parsed device URL: ``scheme://target?key=value&...``."""

    raw: str
    scheme: str
    target: str
    params: dict[str, str]

    @classmethod
    def parse(cls, url: str) -> "DeviceUrl":
        parts = urlsplit(url)
        if not parts.scheme or "://" not in url:
            raise ConfigError(f"device URL {url!r} has no scheme (expected e.g. sim://emht or fob:///dev/ttyUSB0)")
        params = dict(parse_qsl(parts.query, keep_blank_values=True, strict_parsing=False))
        return cls(url, parts.scheme, (parts.netloc + parts.path), params)

    def take(self, allowed: dict[str, type], defaults: dict[str, Any]) -> dict[str, Any]:
        """Typed parameters; refuse unknown keys and unparsable values (never guess)."""
        unknown = sorted(set(self.params) - set(allowed))
        if unknown:
            raise ConfigError(f"{self.raw}: unknown parameter(s) {', '.join(unknown)} (known: {', '.join(sorted(allowed))})")
        values = dict(defaults)
        for key, text in self.params.items():
            try:
                values[key] = allowed[key](text)
            except ValueError:
                raise ConfigError(f"{self.raw}: {key}={text!r} is not a valid {allowed[key].__name__}") from None
        return values

    def redacted(self) -> str:
        """The URL with any password removed (for manifests and logs)."""
        parts = urlsplit(self.raw)
        if parts.password is None and "password" not in self.params:
            return self.raw
        netloc = parts.hostname or ""
        if parts.port:
            netloc += f":{parts.port}"
        query = "&".join(f"{k}={v}" for k, v in self.params.items() if k != "password")
        return f"{parts.scheme}://{netloc}{parts.path}" + (f"?{query}" if query else "")


@dataclass
class DeviceContext:
    """What every backend is built with, as ``Backend(name, url, context)``: the host ``clock``, the
    session start ``start_ns`` (sample k of a paced device is due at start + k / rate), the session
    ``seed`` (a URL's ``seed=`` wins), the absolute ``session_dir`` for backends that write files into the
    session (empty: none), and what a device carries across reconnects (a worker builds one context and
    reuses it for every reopen of its device, so a reopened device continues its sequence)."""

    clock: HostClock
    start_ns: int = 0
    seed: int = 0
    session_dir: str = ""
    carried: dict[str, Any] = field(default_factory=dict, repr=False)

    @classmethod
    def describing(cls, seed: int = 0) -> "DeviceContext":
        """A context for backends built only for their stream layout and settings (nothing is opened)."""
        return cls(HostClock(0), 0, seed)

    def carry(self, key: str, factory: Callable[[], T]) -> T:
        """The state kept under ``key`` across reconnects (made by ``factory`` the first time)."""
        if key not in self.carried:
            self.carried[key] = factory()
        return self.carried[key]


@dataclass
class DeviceCounters:
    """Problems a backend saw and handled: nothing is discarded without being counted."""

    corrupt: int = 0
    discarded_bytes: int = 0
    extra: dict[str, int] = field(default_factory=dict)


class Device(ABC):
    """One opened device. Lives entirely inside its worker process."""

    kind: str = ""

    def __init__(self, name: str, url: DeviceUrl) -> None:
        self.name = name
        self.url = url
        self.counters = DeviceCounters()
        self.final_info: dict[str, Any] = {}  # what ``finish`` checked; merged into the manifest's info

    @property
    @abstractmethod
    def streams(self) -> list[StreamSpec]:
        """The streams this device produces, known before it is opened."""

    @abstractmethod
    def open(self) -> dict[str, Any]:
        """Connect; return what is known of the device (serial number, firmware, settings)."""

    @abstractmethod
    def read(self) -> dict[str, list[tuple]]:
        """Block for at most a few ms; return new rows per stream name (possibly none)."""

    def finish(self) -> dict[str, list[tuple]]:
        """The recording is ending normally (called once, before ``close``): stop what the device
        records by itself and return its last rows per stream (e.g. frames only known once a file is
        finalised); put what was checked in ``final_info``. Default: nothing to add."""
        return {}

    def close(self) -> None:
        """Release the device; must be safe to call twice."""

    def settings(self) -> dict[str, Any]:
        """The effective settings (recorded in the manifest)."""
        return {}
