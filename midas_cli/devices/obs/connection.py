"""A connection to obs-websocket v5 through obsws-python: requests, record events, typed errors.

The password comes from the environment or a file of its own (never the URL, argv, logs or
manifest): the file a rig's ``password_file`` names (only its owner may read it, like ssh's keys), the
variable its ``password_env`` names, else ``MIDAS_OBS_PASSWORD``; none if neither is set.
obsws-python logs its connection parameters, password included, at INFO level and every failed
request with a traceback; its loggers are raised to CRITICAL here and errors are reported as
DeviceError with a message instead.
"""

from __future__ import annotations

import logging
import os
import queue
import stat
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from midas_cli.clock import HostClock
from midas_cli.errors import ConfigError, DeviceError

log = logging.getLogger(__name__)

PASSWORD_ENV = "MIDAS_OBS_PASSWORD"
MAX_PASSWORD_FILE = 4096  # bytes
OUTPUTS_SUBSCRIPTION = 1 << 6  # obs-websocket EventSubscription.Outputs (RecordStateChanged)


def resolve_password(password_env: str, password_file: str = "") -> tuple[str, str]:
    """(password, where it came from): the file ``password_file``, else the environment; the source
    names only the file or the variable."""
    if password_file and password_env:
        raise ConfigError("give the OBS password through password_file or password_env, not both")
    if password_file:
        return read_password_file(Path(password_file)), f"file {password_file}"
    if password_env:
        if password_env not in os.environ:
            raise ConfigError(f"the OBS password should come from ${password_env} (password_env), but that "
                              f"environment variable is not set: export it before `midas record`")
        return os.environ[password_env], f"${password_env}"
    if PASSWORD_ENV in os.environ:
        return os.environ[PASSWORD_ENV], f"${PASSWORD_ENV}"
    return "", "none"


def read_password_file(path: Path) -> str:
    """The password in ``path`` (its first line), refused (ConfigError that never shows the content)
    unless it is a regular file of at most 4 KiB owned by this user or root that nobody else may read."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO named by mistake must not block
    except OSError as exc:
        raise ConfigError(f"cannot read the OBS password file {path}: {exc.strerror}") from None
    try:
        _check_password_file(path, os.fstat(fd))
        data = os.read(fd, MAX_PASSWORD_FILE + 1)
    finally:
        os.close(fd)
    try:
        password = data.decode("utf-8").splitlines()[0] if data.strip() else ""
    except UnicodeDecodeError:
        raise ConfigError(f"the OBS password file {path} is not UTF-8 text") from None
    if not password:
        raise ConfigError(f"the OBS password file {path} is empty (expected the password on its first line)")
    return password


def _check_password_file(path: Path, info: os.stat_result) -> None:
    if not stat.S_ISREG(info.st_mode) or info.st_size > MAX_PASSWORD_FILE:
        raise ConfigError(f"the OBS password file {path} must be a regular file of at most "
                          f"{MAX_PASSWORD_FILE} bytes")
    if info.st_uid not in (os.getuid(), 0) or info.st_mode & 0o077:
        raise ConfigError(f"the OBS password file {path} may be read by others (mode "
                          f"{stat.S_IMODE(info.st_mode):04o}, owner uid {info.st_uid}): make it yours and "
                          f"`chmod 600 {path}`")


@dataclass(frozen=True)
class RecordEvent:
    """One RecordStateChanged event: ``state`` e.g. OBS_WEBSOCKET_OUTPUT_STARTED, host time on receipt."""

    state: str
    t_host_ns: int
    output_path: str | None


class ObsConnection:
    """A request client and an event client on the same server; record events go to ``events``."""

    def __init__(self, host: str, port: int, password: str, timeout_s: float, clock: HostClock) -> None:
        self.address = f"{host}:{port}"
        self.clock = clock
        self.events: "queue.Queue[RecordEvent]" = queue.Queue()
        self._lock = threading.Lock()
        _quiet_obsws_logging()
        import obsws_python

        kwargs = {"host": host, "port": port, "password": password, "timeout": timeout_s}
        self._requests = self._connect(obsws_python.ReqClient, kwargs, bool(password))
        try:
            self._events = self._connect(obsws_python.EventClient, {**kwargs, "subs": OUTPUTS_SUBSCRIPTION},
                                         bool(password))
        except DeviceError:
            self._requests.disconnect()
            raise
        self._events.callback.register(self.on_record_state_changed)

    def _connect(self, client_class: type, kwargs: dict[str, Any], have_password: bool) -> Any:
        try:
            return client_class(**kwargs)
        except Exception as exc:  # obsws-python raises OSError, websocket errors and its own, unwrapped
            raise DeviceError(self._connect_error(exc, have_password)) from None

    def _connect_error(self, exc: Exception, have_password: bool) -> str:
        text = f"{type(exc).__name__}: {exc}"
        if "authentication enabled but no password" in str(exc):
            return (f"OBS at {self.address} requires a password: export {PASSWORD_ENV} (or the variable "
                    f"the rig's password_env names, or name a file with password_file) before `midas record`")
        if have_password and not isinstance(exc, OSError):
            return (f"OBS at {self.address} refused the connection ({text}): is the password given (variable "
                    f"or password_file) the one set in OBS > Tools > WebSocket Server Settings?")
        return (f"cannot reach OBS's websocket server at {self.address} ({text}): is OBS running with "
                f"Tools > WebSocket Server Settings > Enable WebSocket server, on this port?")

    def on_record_state_changed(self, data: Any) -> None:
        """obsws-python callback (its event thread): stamp with the host clock on receipt."""
        self.events.put(RecordEvent(data.output_state, self.clock.now_ns(), getattr(data, "output_path", None)))

    def request(self, name: str, data: dict[str, Any] | None = None) -> dict[str, Any]:
        """Send one request; its response data (empty dict if none). DeviceError on any failure."""
        try:
            with self._lock:
                return self._requests.send(name, data, raw=True) or {}
        except Exception as exc:  # a refused request, a timeout or a closed socket
            raise DeviceError(f"OBS at {self.address}: {name} failed: {type(exc).__name__}: {exc}") from None

    def wait_for(self, state: str, timeout_s: float) -> RecordEvent:
        """The next record event in ``state``; transitions (…STARTING, …STOPPING) are skipped, any
        other state (a recording that stopped as it started) is a DeviceError."""
        try:
            while True:
                event = self.events.get(timeout=timeout_s)
                if event.state == state:
                    return event
                if not event.state.endswith("ING"):
                    raise DeviceError(f"OBS at {self.address} reported {event.state} while midas waited for "
                                      f"{state}: see OBS's log (encoder or disk problem?)")
        except queue.Empty:
            raise DeviceError(f"OBS at {self.address} did not report {state} within {timeout_s:.0f} s") from None

    def close(self) -> None:
        """Disconnect both clients; safe to call twice."""
        for client in (getattr(self, "_events", None), getattr(self, "_requests", None)):
            if client is not None:
                try:
                    client.disconnect()
                except Exception:  # already closed by the server: nothing left to release
                    log.debug("OBS client already disconnected")


def _quiet_obsws_logging() -> None:
    logging.getLogger("obsws_python").setLevel(logging.CRITICAL)
