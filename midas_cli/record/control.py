"""The recorder's control socket: a local Unix socket speaking line-delimited JSON (never TCP).

A client connects, sends one JSON object on one line (``{"cmd": "status"}``, ``{"cmd": "mark", "text":
"...", "source": "mark"}``, ``{"cmd": "start"}``, ``{"cmd": "stop"}``) and reads one JSON object on one
line back: ``{"ok": true, ...}`` or ``{"ok": false, "error": "..."}``; then the connection closes.

The socket file has mode 0600 (only its owner may connect). A path that exists is refused unless it is a
stale socket (nobody answers on it), which is replaced. The file is removed when the server closes.

Every `midas record` opens one: ``--control PATH``, or by default ``record-<pid>.sock`` in the user's
private folder (``$XDG_RUNTIME_DIR/midas``, else ``/tmp/midas-<uid>``, mode 0700), so two recordings never
share a socket and `midas mark` finds the running one without a path (and refuses to guess when there
are several).
"""

from __future__ import annotations

import errno
import json
import logging
import os
import re
import select
import socket
import stat
import threading
from pathlib import Path
from typing import Any, Callable

from midas_cli.errors import ConfigError, MidasError, SessionError
from midas_cli.processes import process_alive

log = logging.getLogger(__name__)

MAX_SOCKET_PATH = 107  # bytes: sun_path holds 108 on Linux, one for the terminating NUL
MAX_REQUEST = 64 * 1024
CLIENT_TIMEOUT_S = 10.0
_DEFAULT_NAME = re.compile(r"^record-([0-9]+)\.sock$")

Handler = Callable[[dict[str, Any]], dict[str, Any]]


def default_control_dir() -> Path:
    """The user's private folder for control sockets (created 0700; refused if someone else could use it)."""
    runtime = os.environ.get("XDG_RUNTIME_DIR", "")
    base = Path(runtime) / "midas" if runtime and Path(runtime).is_dir() else Path("/tmp") / f"midas-{os.getuid()}"
    try:
        base.mkdir(mode=0o700, exist_ok=True)
        info = os.lstat(base)
    except OSError as exc:
        raise ConfigError(f"cannot create the control-socket folder {base}: {exc.strerror or exc}; "
                          f"give --control PATH") from exc
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid() or info.st_mode & 0o077:
        raise ConfigError(f"{base} is not a private folder of this user (mode {stat.filemode(info.st_mode)}, "
                          f"owner uid {info.st_uid}); remove it or give --control PATH")
    return base


def default_control_path() -> Path:
    """This process's default control socket: ``<default_control_dir()>/record-<pid>.sock``."""
    return default_control_dir() / f"record-{os.getpid()}.sock"


def running_recordings(folder: Path) -> list[Path]:
    """The default sockets in ``folder`` whose recorder process is alive (sorted); sockets left by a
    recorder that died (killed) are removed on the way."""
    found = []
    for path in sorted(folder.glob("record-*.sock")):
        match = _DEFAULT_NAME.match(path.name)
        if match is None:
            continue
        if process_alive(int(match.group(1))):
            found.append(path)
        elif _is_socket(path):
            path.unlink(missing_ok=True)
    return found


def _is_socket(path: Path) -> bool:
    try:
        return stat.S_ISSOCK(os.lstat(path).st_mode)
    except OSError:
        return False


def check_socket_path(path: Path) -> Path:
    """``path`` made absolute; ConfigError if it is too long for a Unix socket."""
    path = Path(os.path.abspath(path))
    if len(os.fsencode(str(path))) > MAX_SOCKET_PATH:
        raise ConfigError(f"control socket path {path} is {len(os.fsencode(str(path)))} bytes; a Unix socket path "
                          f"holds at most {MAX_SOCKET_PATH}: choose a shorter --control PATH")
    return path


class ControlServer:
    """Listens on ``path`` and answers each request with ``handler(request)`` in its own thread."""

    def __init__(self, path: Path) -> None:
        self.path = check_socket_path(path)
        self._clear_stale()
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old_umask = os.umask(0o177)  # the socket file is born 0600 (bound before any other thread exists)
        try:
            self._sock.bind(str(self.path))
        except OSError as exc:
            self._sock.close()
            raise ConfigError(f"cannot open the control socket {self.path}: {exc.strerror or exc}") from exc
        finally:
            os.umask(old_umask)
        os.chmod(self.path, 0o600)
        self._identity = _identity(self.path)
        self._sock.listen(8)
        self._handler: Handler | None = None
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None

    def _clear_stale(self) -> None:
        """Refuse an existing path unless it is a socket nobody answers on (then remove it)."""
        try:
            info = os.lstat(self.path)
        except FileNotFoundError:
            return
        if not stat.S_ISSOCK(info.st_mode):
            raise ConfigError(f"control socket path {self.path} exists and is not a socket; choose another "
                              f"--control PATH")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.settimeout(1.0)
            probe.connect(str(self.path))
        except (ConnectionRefusedError, FileNotFoundError):
            self.path.unlink(missing_ok=True)  # stale: its recorder is gone
            return
        except OSError as exc:
            raise ConfigError(f"control socket {self.path} exists and cannot be checked ({exc.strerror or exc}); "
                              f"choose another --control PATH") from exc
        finally:
            probe.close()
        raise ConfigError(f"control socket {self.path} is in use by a running recording; stop it, or give "
                          f"this one another --control PATH")

    def serve(self, handler: Handler) -> None:
        """Start answering requests with ``handler`` (called in the server's thread)."""
        self._handler = handler
        self._thread = threading.Thread(target=self._loop, name="midas-control", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop answering and remove the socket file (if it is still the one this server made)."""
        self._closing.set()
        if self._thread is not None:
            self._thread.join(timeout=CLIENT_TIMEOUT_S + 1.0)
        self._sock.close()
        if _identity(self.path) == self._identity:
            self.path.unlink(missing_ok=True)

    def __enter__(self) -> "ControlServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _loop(self) -> None:
        while not self._closing.is_set():
            ready, _, _ = select.select([self._sock], [], [], 0.1)
            if not ready:
                continue
            try:
                conn, _ = self._sock.accept()
            except OSError:
                continue
            with conn:
                try:
                    self._answer(conn)
                except OSError as exc:  # the client went away: its problem, not the recording's
                    log.info("control client: %s", exc)

    def _answer(self, conn: socket.socket) -> None:
        conn.settimeout(CLIENT_TIMEOUT_S)
        try:
            request = json.loads(_read_line(conn))
            if not isinstance(request, dict):
                raise ValueError("expected a JSON object")
        except ValueError as exc:
            reply: dict[str, Any] = {"ok": False, "error": f"bad request: {exc}"}
        else:
            try:
                reply = {"ok": True, **self._handler(request)}  # type: ignore[misc]
            except MidasError as exc:
                reply = {"ok": False, "error": str(exc), "exit_code": exc.exit_code}
            except Exception as exc:  # never let a request end the recording; say what happened
                log.exception("control request %s failed", request.get("cmd"))
                reply = {"ok": False, "error": f"internal error: {type(exc).__name__}: {exc}"}
        conn.sendall((json.dumps(reply, default=str) + "\n").encode())


def _identity(path: Path) -> tuple[int, int] | None:
    try:
        info = os.lstat(path)
    except OSError:
        return None
    return (info.st_dev, info.st_ino)


def _read_line(conn: socket.socket) -> bytes:
    data = b""
    while b"\n" not in data:
        chunk = conn.recv(4096)
        if not chunk:
            break
        data += chunk
        if len(data) > MAX_REQUEST:
            raise ValueError(f"request longer than {MAX_REQUEST} bytes")
    return data.split(b"\n", 1)[0]


def send_request(path: Path, request: dict[str, Any], timeout_s: float = CLIENT_TIMEOUT_S) -> dict[str, Any]:
    """Send ``request`` to the recorder listening on ``path`` and return its reply. SessionError when no
    recorder answers there."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(timeout_s)
    try:
        try:
            sock.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError, NotADirectoryError) as exc:
            raise SessionError(f"no recording is running at {path} ({_reason(exc)})") from exc
        sock.sendall((json.dumps(request) + "\n").encode())
        line = _read_line(sock)
    except socket.timeout as exc:
        raise SessionError(f"the recorder at {path} did not answer within {timeout_s:g} s") from exc
    except OSError as exc:
        raise SessionError(f"cannot talk to the recorder at {path}: {exc.strerror or exc}") from exc
    finally:
        sock.close()
    try:
        reply = json.loads(line)
    except ValueError as exc:
        raise SessionError(f"the recorder at {path} answered {line[:60]!r}, not JSON") from exc
    if not isinstance(reply, dict):
        raise SessionError(f"the recorder at {path} answered {line[:60]!r}, not a JSON object")
    return reply


def _reason(exc: OSError) -> str:
    return "no such socket" if exc.errno in (errno.ENOENT, errno.ENOTDIR) else "nobody listens on it"
