"""What every device backend provides to the recorder's worker processes.

A backend is opened from a URL (``sim://emht?rate=240``); real, emulated and simulated backends
share this interface and the same worker code path. ``read`` returns rows whose first two values
are ``seq`` (the device's counter) and ``t_host_ns`` (host clock when the bytes were read).
"""

from __future__ import annotations

import re
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, Callable, TypeVar
from urllib.parse import parse_qsl, unquote_plus, urlsplit

from midas_cli.clock import HostClock
from midas_cli.errors import ConfigError
from midas_cli.session.schema import StreamSpec

T = TypeVar("T")
# Words that make a URL parameter or a rig key a secret (matched against the lower-cased key and its
# parts split at '_', '-', '.'); the names of where a secret is kept are not secrets themselves.
SECRET_WORDS = frozenset({"password", "passwd", "pass", "pw", "pwd", "passphrase", "secret", "token", "apikey",
                          "key", "auth", "credential", "credentials"})
NOT_SECRET = frozenset({"password_env", "password_file"})
WHERE_PASSWORDS_GO = ("put it in an environment variable (OBS: MIDAS_OBS_PASSWORD, or the variable a rig's "
                      "password_env names) or in a file only you can read (a rig's password_file)")
REDACTED = "***"


def is_secret_key(key: str) -> bool:
    """True for a parameter or key name that holds a secret (``password``, ``Pw``, ``api_token``...)."""
    lowered = key.strip().lower()
    if lowered in NOT_SECRET:
        return False
    return lowered in SECRET_WORDS or any(part in SECRET_WORDS for part in re.split(r"[_.-]", lowered))


def user_part_end(text: str) -> int:
    """Index of the '@' that ends a user part (``user:password@``) in a URL, -1 if none: the last '@'
    outside the query's values (a password holding '/' or '?' moves the host into the path or the
    query, so the '@' is looked for there too)."""
    before, _, query = text.partition("?")
    end, offset = before.rfind("@"), len(before) + 1
    for pair in query.split("&"):
        key = pair.partition("=")[0]
        if "@" in key:
            end = offset + key.rfind("@")
        offset += len(pair) + 1
    return end


def redact_url(text: str) -> str:
    """``text`` safe to show or store: a user part (``user:password@``) and the values of secret
    parameters (``?pw=``, ``?Password=``...) become ``***``. Never raises, whatever ``text`` holds."""
    end = user_part_end(text)
    if end >= 0:
        scheme_end = text.find("://")
        start = scheme_end + 3 if 0 <= scheme_end < end else 0
        text = text[:start] + REDACTED + text[end:]
    before, mark, query = text.partition("?")
    return before + mark + "&".join(_redacted_pair(pair) for pair in query.split("&")) if mark else before


def _redacted_pair(pair: str) -> str:
    key, sep, _ = pair.partition("=")
    return f"{key}{sep}{REDACTED}" if is_secret_key(unquote_plus(key)) else pair


def _refuse_credentials(url: str, params: list[tuple[str, str]]) -> None:
    """ConfigError (naming neither the secret nor anything that holds it) for a user part or a secret
    parameter in a device URL: they would reach shell history, process lists, logs and the manifest."""
    if user_part_end(url) >= 0:
        raise ConfigError(f"device URL {redact_url(url)}: a user or password before '@' is refused (it would "
                          f"end up in shell history, process lists, logs and the session manifest); remove it "
                          f"and {WHERE_PASSWORDS_GO}")
    secret = [key for key, _ in params if is_secret_key(key)]
    if secret:
        raise ConfigError(f"device URL {redact_url(url)}: parameter {secret[0]!r} holds a secret and is refused "
                          f"(it would end up in shell history, process lists, logs and the session manifest); "
                          f"{WHERE_PASSWORDS_GO}")


@dataclass(frozen=True)
class DeviceUrl:
    """A parsed device URL: ``scheme://target?key=value&...``."""

    raw: str
    scheme: str
    target: str
    params: dict[str, str]

    @classmethod
    def parse(cls, url: str) -> "DeviceUrl":
        """Parse ``url``; ConfigError for no scheme, an unparsable URL or credentials in it (user part,
        secret parameters), the message showing the URL redacted."""
        try:
            parts = urlsplit(url)
        except ValueError as exc:  # e.g. an unclosed '[' of an IPv6 address
            raise ConfigError(f"device URL {redact_url(url)!r} is not a valid URL ({exc})") from None
        if not parts.scheme or "://" not in url:
            raise ConfigError(f"device URL {redact_url(url)!r} has no scheme (expected e.g. sim://emht or "
                              f"fob:///dev/ttyUSB0)")
        pairs = parse_qsl(parts.query, keep_blank_values=True, strict_parsing=False)
        _refuse_credentials(url, pairs)
        params = dict(pairs)
        return cls(url, parts.scheme, (parts.netloc + parts.path), params)

    def take(self, allowed: dict[str, type], defaults: dict[str, Any]) -> dict[str, Any]:
        """Typed parameters; refuse unknown keys and unparsable values (never guess)."""
        unknown = sorted(set(self.params) - set(allowed))
        if unknown:
            raise ConfigError(f"{self.redacted()}: unknown parameter(s) {', '.join(unknown)} (known: {', '.join(sorted(allowed))})")
        values = dict(defaults)
        for key, text in self.params.items():
            try:
                values[key] = allowed[key](text)
            except ValueError:
                raise ConfigError(f"{self.redacted()}: {key}={text!r} is not a valid {allowed[key].__name__}") from None
        return values

    def redacted(self) -> str:
        """The URL as shown and stored (manifests, logs, the screen): see :func:`redact_url`."""
        return redact_url(self.raw)


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

    def close(self) -> None:  # noqa: B027 - a hook: most devices hold nothing to release
        """Release the device; must be safe to call twice."""

    def settings(self) -> dict[str, Any]:
        """The effective settings (recorded in the manifest)."""
        return {}
