"""One base for the serial-device emulators served on pseudo-terminals (trakSTAR, FPS pedal board).

:class:`PtyPort` owns the pty: ``os.openpty`` in raw mode, a non-blocking master, and optionally a
``link``: a pty cannot keep its /dev/pts number across a close, so the link is a symlink that always
points at the current pty (replaced atomically at each plug, removed while unplugged): open the link.

:class:`Faults` is the one fault vocabulary (times in seconds since the emulator started, probabilities
per byte): ``corrupt`` (the byte is replaced by line noise), ``drop`` (the byte is lost), one stall
window ``stall_at``/``stall_for`` (the device sends nothing; what falls due meanwhile is skipped) and
one unplug window ``unplug_at``/``unplug_for`` (the pty is closed and reopened at the link later).

:class:`PtyEmulator` serves a device from a thread (``start``/``stop``/``join``/``serve_for``) or the
caller's thread (``serve``), applies the faults (plus manual :meth:`~PtyEmulator.stall`,
:meth:`~PtyEmulator.unplug`, :meth:`~PtyEmulator.replug`) and reports what it sent with one
:meth:`~PtyEmulator.summary`. An exception in the serving thread is logged, stored and re-raised (as a
DeviceError) by the next ``serve_for``, ``join`` or ``stop``: never swallowed. Subclasses implement
``_step`` (one turn of the device's loop while plugged) and may hook plugging and the summary.

With a ``send_log`` path an emulator logs when each record's last byte went out
(:mod:`~midas_cli.devices.send_log`): :meth:`~PtyEmulator._write` then notes ``last_write_ns``, the
monotonic time its ``os.write`` returned, and the device logs its records with it.
"""

from __future__ import annotations

import json
import logging
import math
import os
import threading
import time
import tty
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from midas_cli.devices.send_log import SendLog
from midas_cli.errors import ConfigError, DeviceError

log = logging.getLogger(__name__)

UNPLUGGED_WAIT_S = 0.01


@dataclass(frozen=True)
class Faults:
    """Injected faults, validated here for every emulator (see the module docstring)."""

    corrupt: float = 0.0
    drop: float = 0.0
    stall_at: float = -1.0
    stall_for: float = 0.0
    unplug_at: float = -1.0
    unplug_for: float = 0.0

    def __post_init__(self) -> None:
        for name in ("corrupt", "drop"):
            value = getattr(self, name)
            if not 0.0 <= value < 1.0:
                raise ConfigError(f"{name} must be a probability in [0, 1), got {value}")
        for name in ("stall_at", "unplug_at", "stall_for", "unplug_for"):
            if not math.isfinite(getattr(self, name)):
                raise ConfigError(f"{name} must be finite, got {getattr(self, name)}")
        for name in ("stall_for", "unplug_for"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be >= 0 s, got {getattr(self, name)}")

    @property
    def damages_bytes(self) -> bool:
        return bool(self.corrupt or self.drop)

    def stalled(self, t: float) -> bool:
        """Is ``t`` (s since start) inside the stall window?"""
        return 0 <= self.stall_at <= t < self.stall_at + self.stall_for

    def unplugged(self, t: float) -> bool:
        """Is ``t`` (s since start) inside the unplug window?"""
        return 0 <= self.unplug_at <= t < self.unplug_at + self.unplug_for


class PtyPort:
    """A pty pair (raw, master non-blocking) and the symlink that follows it across replugs."""

    def __init__(self, link: str | Path | None) -> None:
        self.link = str(link) if link else None
        self.master = self.slave = -1
        self.pty_path = ""

    @property
    def plugged(self) -> bool:
        return self.master >= 0

    @property
    def path(self) -> str:
        """The path a host opens: the link when configured, else the pty itself."""
        return self.link or self.pty_path

    def open(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line editing: the line discipline must not touch bytes
        os.set_blocking(master, False)
        self.master, self.slave = master, slave
        self.pty_path = os.ttyname(slave)
        if self.link:
            temporary = f"{self.link}.{os.getpid()}.tmp"
            if os.path.lexists(temporary):
                os.unlink(temporary)
            os.symlink(self.pty_path, temporary)
            os.replace(temporary, self.link)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            if fd >= 0:
                os.close(fd)
        self.master = self.slave = -1
        if self.link and os.path.islink(self.link):
            os.unlink(self.link)


class PtyEmulator:
    """Base of the pty emulators: plugging, faults, the serving thread, the summary."""

    label = "pty"
    send_log_identity: tuple[str, ...] = ("record",)  # the columns naming a record in the send log

    def __init__(self, faults: Faults, link: str | Path | None, seed: int,
                 send_log: str | Path | None = None) -> None:
        if faults.unplug_at >= 0 and not link:
            raise ConfigError("an unplug changes the pty's path: give a link path that follows it")
        self.faults = faults
        self.port = PtyPort(link)
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._error_raised = False
        self._final_summary: dict[str, Any] | None = None
        self._t0 = time.monotonic()
        self._stall_until = 0.0
        self._unplug_until = 0.0
        self.bytes_corrupted = 0
        self.bytes_dropped = 0
        self.unplugs: list[dict[str, Any]] = []
        self.send_log = SendLog(send_log, self.send_log_identity) if send_log else None
        self.last_write_ns = 0  # monotonic ns when the last os.write returned (kept only with a send log)

    # -- public API ---------------------------------------------------------------------------------
    @property
    def path(self) -> str:
        """The path a host opens: the link when configured (stable across replugs), else the pty."""
        return self.port.path

    @property
    def pty_path(self) -> str:
        return self.port.pty_path

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> "PtyEmulator":
        """Plug in (if not yet) and serve from a daemon thread."""
        if not self.port.plugged and not self.unplugs:
            self._t0 = time.monotonic()
            self._plug()
        self._thread = threading.Thread(target=self._run, name=f"{self.label}-emulator", daemon=True)
        self._thread.start()
        return self

    def join(self, timeout: float | None = None) -> None:
        """Wait for the serving thread to end; re-raise an error it met."""
        if self._thread is not None:
            self._thread.join(timeout)
        self._raise_error()

    def stop(self) -> dict[str, Any]:
        """Stop serving, close the pty, remove the link; return the summary. Re-raises an error the
        serving thread met (unless ``serve_for`` or ``join`` already did)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            if self._thread.is_alive():  # closing the pty under it could let it write into a reused fd
                raise DeviceError(f"the {self.label} emulator's thread did not stop within 5 s")
        if self._final_summary is None:
            self._final_summary = self.summary()
        self.port.close()
        if self.send_log is not None:
            self.send_log.close()
        self._raise_error()
        return self._final_summary

    def serve_for(self, duration_s: float | None, should_stop: Callable[[], bool] = lambda: False) -> None:
        """Serve from the thread until ``duration_s`` has passed or ``should_stop()`` is true; raise
        the thread's error if it fails meanwhile."""
        if not self.running and self._error is None:
            self.start()
        deadline = None if duration_s is None else time.monotonic() + duration_s
        while not should_stop() and (deadline is None or time.monotonic() < deadline):
            if not self.running:
                self._raise_error()
                raise DeviceError(f"the {self.label} emulator stopped unexpectedly")
            time.sleep(0.05)
        self._raise_error()

    def __enter__(self) -> "PtyEmulator":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stall(self, for_s: float) -> None:
        """Send nothing for ``for_s`` seconds from now (what falls due meanwhile is skipped)."""
        self._stall_until = time.monotonic() + for_s

    def unplug(self, for_s: float | None = None) -> None:
        """Pull the cable (the serving thread closes the pty within ~10 ms); plug it back in after
        ``for_s`` seconds, or at :meth:`replug` when None."""
        self._unplug_until = math.inf if for_s is None else time.monotonic() + for_s

    def replug(self) -> None:
        """End a manual unplug (the scheduled unplug window still applies)."""
        self._unplug_until = 0.0

    def set_unplugged(self, unplugged: bool) -> None:
        """Pull the cable (True) or plug it back in (False)."""
        self.unplug() if unplugged else self.replug()

    def summary(self) -> dict[str, Any]:
        """What was sent: the common part here, the device's own in :meth:`_summary`."""
        if self._final_summary is not None:
            return self._final_summary
        with self._lock:
            return {"path": self.path, "pty": self.port.pty_path, "faults": asdict(self.faults),
                    "bytes_corrupted": self.bytes_corrupted, "bytes_dropped": self.bytes_dropped,
                    "unplugs": [dict(u) for u in self.unplugs], **self._summary()}

    def write_summary(self, path: Path | str) -> None:
        Path(path).write_text(json.dumps(self.summary()) + "\n", encoding="utf-8")

    # -- the loop -----------------------------------------------------------------------------------
    def serve(self) -> None:
        """Run until ``stop()``: follow the unplug windows, else let the device take a step."""
        while not self._stop.is_set():
            now = time.monotonic()
            wanted = self._plug_wanted(now)
            if self.port.plugged and not wanted:
                self._unplug_now()
            elif not self.port.plugged and wanted:
                self._plug()
            elif not self.port.plugged:
                self._while_unplugged(now)
                time.sleep(UNPLUGGED_WAIT_S)
            else:
                self._step(now)

    def _run(self) -> None:
        try:
            self.serve()
        except BaseException as exc:  # re-raised by serve_for/join/stop: never swallowed
            log.exception("the %s emulator's thread failed", self.label)
            self._error = exc

    def _raise_error(self) -> None:
        if self._error is not None and not self._error_raised:
            self._error_raised = True
            raise DeviceError(f"the {self.label} emulator failed: {self._error!r}") from self._error

    def _plug_wanted(self, now: float) -> bool:
        return now >= self._unplug_until and not self.faults.unplugged(now - self._t0)

    def _stalled(self, now: float) -> bool:
        """Is monotonic time ``now`` inside a stall (manual or scheduled)?"""
        return now < self._stall_until or self.faults.stalled(now - self._t0)

    def _plug(self) -> None:
        with self._lock:
            self.port.open()
            if self.unplugs:
                self.unplugs[-1].update(replugged_ns=time.time_ns(), path=self.port.pty_path)
        log.info("%s emulator serving on %s", self.label, self.path)
        self._on_plug(time.monotonic())

    def _unplug_now(self) -> None:
        with self._lock:
            self.port.close()
            self.unplugs.append({"unplugged_ns": time.time_ns(), "replugged_ns": None, "path": None})
        self._on_unplug()

    def _write(self, data: bytes) -> int:
        """Write what the pty takes now; returns the bytes written (-1: the pty is gone). With a send
        log, ``last_write_ns`` is when the write returned."""
        try:
            written = os.write(self.port.master, data)
        except (BlockingIOError, InterruptedError):
            return 0
        except OSError:
            return -1
        if self.send_log is not None:
            self.last_write_ns = time.monotonic_ns()
        return written

    def _read(self, size: int = 4096) -> bytes:
        """What the host sent ('' when nothing or nobody has the pty open, EIO)."""
        try:
            return os.read(self.port.master, size)
        except OSError:
            return b""

    # -- byte faults --------------------------------------------------------------------------------
    def _damage(self, data: bytes) -> bytes:
        """``data`` through the line faults: each byte dropped with p=``drop``, else replaced by
        :meth:`_noise` with p=``corrupt`` (one roll per byte); counted."""
        faults = self.faults
        if not faults.damages_bytes or not data:
            return data
        raw = np.frombuffer(data, dtype=np.uint8).copy()
        roll = self._rng.random(len(raw))
        dropped = roll < faults.drop
        corrupted = ~dropped & (roll < faults.drop + faults.corrupt)
        if corrupted.any():
            raw[corrupted] = self._noise(raw[corrupted])
        self.bytes_corrupted += int(corrupted.sum())
        self.bytes_dropped += int(dropped.sum())
        return raw[~dropped].tobytes()

    def _noise(self, raw: np.ndarray) -> np.ndarray:
        """What corrupted bytes become; default: XOR with a random non-zero byte (never unchanged)."""
        return raw ^ self._rng.integers(1, 256, len(raw), dtype=np.uint8)

    # -- hooks --------------------------------------------------------------------------------------
    def _step(self, now: float) -> None:
        """One turn of the device's loop while plugged in (wait at most ~10-20 ms)."""
        raise NotImplementedError

    def _on_plug(self, now: float) -> None:
        """The pty was (re)opened at monotonic time ``now``."""

    def _on_unplug(self) -> None:
        """The pty was closed."""

    def _while_unplugged(self, now: float) -> None:
        """Called every ~10 ms while unplugged."""

    def _summary(self) -> dict[str, Any]:
        """The device's part of the summary (called under the lock)."""
        return {}
