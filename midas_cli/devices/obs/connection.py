"""A connection to obs-websocket v5 through obsws-python: requests, record events, typed errors.

The password comes from an environment variable only (never the URL, argv, logs or manifest):
the one a rig's ``password_env`` names, else ``MIDAS_OBS_PASSWORD``; none if neither is set.
obsws-python logs its connection parameters, password included, at INFO level and every failed
request with a traceback; its loggers are raised to CRITICAL here and errors are reported as
DeviceError with a message instead.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
from dataclasses import dataclass
from typing import Any

from midas_cli.clock import HostClock
from midas_cli.errors import ConfigError, DeviceError

log = logging.getLogger(__name__)

PASSWORD_ENV = "MIDAS_OBS_PASSWORD"
OUTPUTS_SUBSCRIPTION = 1 << 6  # obs-websocket EventSubscription.Outputs (RecordStateChanged)


def resolve_password(password_env: str) -> tuple[str, str]:
    """(password, where it came from) from the environment; the source names only the variable."""
    if password_env:
        if password_env not in os.environ:
            raise ConfigError(f"the OBS password should come from ${password_env} (password_env), but that "
                              f"environment variable is not set: export it before `midas record`")
        return os.environ[password_env], f"${password_env}"
    if PASSWORD_ENV in os.environ:
        return os.environ[PASSWORD_ENV], f"${PASSWORD_ENV}"
    return "", "none"


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
                    f"the rig's password_env names) before `midas record`")
        if have_password and not isinstance(exc, OSError):
            return (f"OBS at {self.address} refused the connection ({text}): is the password in the "
                    f"environment variable the one set in OBS > Tools > WebSocket Server Settings?")
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
