"""The USB-serial adapter behind a serial port, found through sysfs, and its latency settings.

A USB-serial adapter holds received bytes until its buffer fills or its latency timer runs out (FTDI,
driver ``ftdi_sio``: 16 ms by default), which delays and bunches the host stamps of a device behind it.
For a port such as ``/dev/ttyUSB0`` (or a ``/dev/serial/by-id/...`` link to it) this module follows
``<sysfs>/class/tty/ttyUSB0/device`` to the kernel's device folder, reads the driver's name (its
``driver`` link), the USB vendor and product ids (``idVendor``/``idProduct``, up the tree) and, where
the driver has one, the latency timer (``latency_timer`` in the device folder, also reached as
``<sysfs>/bus/usb-serial/devices/ttyUSB0/latency_timer``). :func:`tune_latency_timer` sets the timer
to 1 ms where this user may write it; else the report says how (a one-off ``tee`` or a udev rule).
:func:`set_low_latency` sets the tty's ASYNC_LOW_LATENCY flag on an open port's file descriptor
(``TIOCGSERIAL``/``TIOCSSERIAL``); pseudo-terminals and emulators do not support it, quietly.

The sysfs root is ``/sys`` unless ``MIDAS_SYSFS_ROOT`` (or the ``root`` argument) names another tree
(tests build a fake one). Nothing read from sysfs is trusted: links that leave the tree, unreadable
files and values that are not numbers are reported as unknown, never raised.
"""

from __future__ import annotations

import array
import fcntl
import logging
import os
import re
import select
import termios
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

SYSFS_ROOT_ENV = "MIDAS_SYSFS_ROOT"
WANTED_LATENCY_MS = 1
ASYNC_LOW_LATENCY = 0x2000  # serial_struct.flags bit (linux/tty_flags.h)
SERIAL_FLAGS_INDEX = 4  # serial_struct: type, line, port, irq, flags, ... (ints)
UDEV_RULES_FILE = "/etc/udev/rules.d/99-midas-ftdi.rules"
ADAPTER_NAMES = re.compile(r"tty(USB|ACM)\d+")
USB_ID = re.compile(r"[0-9a-fA-F]{4}")
MAX_DEPTH = 16  # folders walked up from the tty's device looking for the USB device


@dataclass
class AdapterReport:
    """What is in force on one serial port. ``adapter`` is "usb", "not usb" (a pty, a built-in UART, a
    network URL) or "unknown" (no sysfs); latency times in ms (None: the driver has no latency timer);
    ``low_latency`` "on", "off", "unsupported", or None where no open port was asked; ``note`` what the
    user should know (how to set the timer when midas may not)."""

    port: str
    tty: str = ""
    adapter: str = "not usb"
    driver: str = ""
    vid_pid: str = ""
    product: str = ""
    latency_timer_path: str = ""
    latency_timer_before_ms: int | None = None
    latency_timer_ms: int | None = None
    low_latency: str | None = None
    note: str = ""

    def as_dict(self) -> dict[str, Any]:
        """The report as stored in the manifest and printed by ``--json``."""
        return asdict(self)

    def summary(self) -> str:
        """One line: ``/dev/ttyUSB0: USB 0403:6001 (FTDI FT232R), driver ftdi_sio, low-latency flag on,
        latency timer 16 -> 1 ms``; where the timer could not be set, how to set it instead."""
        if self.adapter != "usb":
            parts = [f"{self.port}: {self.note or 'not a USB serial adapter'}"]
        else:
            product = f" ({self.product})" if self.product else ""
            parts = [f"{self.port}: USB {self.vid_pid or '?'}{product}, driver {self.driver or '?'}"]
        if self.low_latency is not None:
            parts.append(f"low-latency flag {self.low_latency}")
        if self.adapter == "usb":
            parts.append(self.note or self._latency_text())
        return ", ".join(parts)

    def _latency_text(self) -> str:
        before, now = self.latency_timer_before_ms, self.latency_timer_ms
        if not self.latency_timer_path:
            return "no latency timer"
        if now is None:
            return "latency timer unreadable"
        changed = before is not None and before != now
        return f"latency timer {before} -> {now} ms" if changed else f"latency timer {now} ms"


def sysfs_root(root: str | Path | None = None) -> Path:
    """``root``, else ``$MIDAS_SYSFS_ROOT``, else ``/sys``."""
    return Path(root if root is not None else (os.environ.get(SYSFS_ROOT_ENV) or "/sys"))


def adapter_ports(root: str | Path | None = None) -> list[str]:
    """``/dev/ttyUSB*`` and ``/dev/ttyACM*`` as the kernel lists them under ``<sysfs>/class/tty``, sorted."""
    try:
        names = [entry.name for entry in (sysfs_root(root) / "class" / "tty").iterdir()]
    except OSError:
        return []
    return [f"/dev/{name}" for name in sorted(names, key=_natural) if ADAPTER_NAMES.fullmatch(name)]


def _natural(name: str) -> tuple[str, int]:
    digits = re.search(r"\d+$", name)
    return (name[:digits.start()], int(digits.group())) if digits else (name, -1)


def find_adapter(port: str, root: str | Path | None = None) -> AdapterReport:
    """The adapter behind ``port`` (a device path or a pyserial URL), read from sysfs; changes nothing."""
    try:
        return _find_adapter(port, sysfs_root(root))
    except OSError as exc:  # a folder of the tree this user may not read
        return AdapterReport(port, adapter="unknown", note=f"sysfs unreadable: {exc}")


def _find_adapter(port: str, base: Path) -> AdapterReport:
    report = AdapterReport(port)
    if "://" in port:
        report.note = "not a local serial port (a URL)"
        return report
    real = Path(os.path.realpath(port))
    if real.parent == Path("/dev/pts"):
        report.note = "not a USB serial adapter (a pseudo-terminal)"
        return report
    if not (base / "class" / "tty").is_dir():
        report.adapter, report.note = "unknown", f"no sysfs at {base}"
        return report
    device = _inside(base, base / "class" / "tty" / real.name / "device") if real.parent == Path("/dev") else None
    usb = _usb_device(base, device) if device is not None else None
    if usb is None:
        report.note = "not a USB serial adapter"
        return report
    report.tty, report.adapter, report.driver = real.name, "usb", _driver(device)
    report.vid_pid = f"{_read_id(usb / 'idVendor')}:{_read_id(usb / 'idProduct')}"
    report.product = " ".join(filter(None, (_read_text(usb / "manufacturer"), _read_text(usb / "product"))))
    timer = device / "latency_timer"
    if timer.is_file():
        by_bus = base / "bus" / "usb-serial" / "devices" / real.name / "latency_timer"
        report.latency_timer_path = str(by_bus if by_bus.is_file() else timer)
        report.latency_timer_before_ms = report.latency_timer_ms = _read_int(timer)
    return report


def _inside(base: Path, link: Path) -> Path | None:
    """``link`` resolved, None when it does not exist or leads out of the sysfs tree ``base``."""
    try:
        target = link.resolve(strict=True)
        target.relative_to(base.resolve(strict=True))
    except (OSError, ValueError, RuntimeError):
        return None
    return target if target.is_dir() else None


def _usb_device(base: Path, device: Path) -> Path | None:
    """The first folder at or above ``device`` (inside ``base``) with ``idVendor`` and ``idProduct``."""
    top = base.resolve()
    folder = device
    for _ in range(MAX_DEPTH):
        if (folder / "idVendor").is_file() and (folder / "idProduct").is_file():
            return folder
        if folder == top or folder.parent == folder:
            return None
        folder = folder.parent
    return None


def _driver(device: Path) -> str:
    try:
        return os.path.basename(os.readlink(device / "driver"))
    except OSError:
        return ""


def _read_text(path: Path, limit: int = 128) -> str:
    """A sysfs attribute's text (printable, stripped, at most ``limit`` characters), '' if unreadable."""
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            text = f.read(limit)
    except OSError:
        return ""
    return "".join(c for c in text.strip() if c.isprintable())


def _read_id(path: Path) -> str:
    text = _read_text(path, 8).lower()
    return text if USB_ID.fullmatch(text) else "?"


def _read_int(path: Path) -> int | None:
    text = _read_text(path, 16)
    return int(text) if text.isascii() and text.isdigit() else None


def tune_latency_timer(report: AdapterReport, wanted_ms: int = WANTED_LATENCY_MS) -> AdapterReport:
    """Set the adapter's latency timer to ``wanted_ms`` where this user may write it; else put in
    ``report.note`` how to (the one-off ``tee`` and the udev rule). Returns ``report``, updated."""
    if not report.latency_timer_path or report.latency_timer_ms is None or report.latency_timer_ms <= wanted_ms:
        return report
    path = Path(report.latency_timer_path)
    if not _may_write(path):
        report.note = latency_hint(report, wanted_ms, "not permitted to change it here")
        return report
    try:
        path.write_text(f"{wanted_ms}\n")
    except OSError as exc:
        report.note = latency_hint(report, wanted_ms, f"setting it failed: {exc.strerror or exc}")
        return report
    report.latency_timer_ms = _read_int(path)
    if report.latency_timer_ms != wanted_ms:
        report.note = latency_hint(report, wanted_ms, f"the driver kept {report.latency_timer_ms} ms")
    return report


def _may_write(path: Path) -> bool:
    """Whether this user may write the sysfs attribute ``path``: a sysfs attribute without a write bit
    has no setter, which even root cannot write, so root needs a write bit; others need access."""
    try:
        mode = path.stat().st_mode
    except OSError:
        return False
    return bool(mode & 0o222) if os.geteuid() == 0 else os.access(path, os.W_OK)


def latency_hint(report: AdapterReport, wanted_ms: int, why: str) -> str:
    """How to set the latency timer of ``report``'s adapter by hand, once and for good."""
    real_path = f"/sys/bus/usb-serial/devices/{report.tty}/latency_timer"
    rule = (f'ACTION=="add", SUBSYSTEM=="usb-serial", DRIVER=="{report.driver or "ftdi_sio"}", '
            f'ATTR{{latency_timer}}="{wanted_ms}"')
    return (f"latency timer {report.latency_timer_ms} ms, not {wanted_ms} ({why}): once with "
            f"`echo {wanted_ms} | sudo tee {real_path}`, for good with the udev rule '{rule}' in {UDEV_RULES_FILE} "
            f"(then `sudo udevadm control --reload && sudo udevadm trigger`, or replug)")


def set_low_latency(fd: int | None) -> str | None:
    """Set ASYNC_LOW_LATENCY on the open tty ``fd``: "on", "off" (the driver refused it), "unsupported"
    (a pty, an emulator, not Linux), None when there is no descriptor."""
    if fd is None:
        return None
    get, put = getattr(termios, "TIOCGSERIAL", None), getattr(termios, "TIOCSSERIAL", None)
    if get is None or put is None:
        return "unsupported"
    serial = array.array("i", [0] * 32)  # struct serial_struct fits in 32 ints
    try:
        fcntl.ioctl(fd, get, serial)
    except OSError:
        return "unsupported"
    if serial[SERIAL_FLAGS_INDEX] & ASYNC_LOW_LATENCY:
        return "on"
    serial[SERIAL_FLAGS_INDEX] |= ASYNC_LOW_LATENCY
    try:
        fcntl.ioctl(fd, put, serial)
        fcntl.ioctl(fd, get, serial)
    except OSError as exc:
        log.warning("setting the low-latency flag failed: %s", exc)
        return "off"
    return "on" if serial[SERIAL_FLAGS_INDEX] & ASYNC_LOW_LATENCY else "off"


def port_fd(port: object) -> int | None:
    """The file descriptor of an open pyserial port, None for ports without one (``loop://``, ``socket://``)."""
    try:
        return port.fileno()  # type: ignore[attr-defined]
    except (AttributeError, OSError, ValueError):
        return None


def read_available(port: object, fd: int | None, timeout_s: float, limit: int = 65536) -> bytes:
    """What waits on an open pyserial ``port``, else what arrives within ``timeout_s`` (b'' if nothing).

    With the port's file descriptor ``fd`` (``port_fd``): one ``select`` and one ``read`` of everything
    there, where pyserial's ``read(in_waiting)`` costs an ioctl, a select and its own Python loop more
    per call (at 850 lines a second, a few per cent of a core). Without one (``loop://``,
    ``socket://``), pyserial's own read. A port that reports data and then reads none is gone: raised as
    pyserial does (``SerialException``), as is the ``OSError`` of a vanished device."""
    if fd is None:
        return port.read(max(1, port.in_waiting))  # type: ignore[attr-defined]
    if not select.select([fd], [], [], timeout_s)[0]:
        return b""
    try:
        data = os.read(fd, limit)
    except BlockingIOError:  # raced with another reader of the port: nothing for us this time
        return b""
    if not data:
        import serial  # pyserial: only where a port is read

        raise serial.SerialException("the port reported data but read none (disconnected, or opened twice?)")
    return data


def inspect_port(port: str, root: str | Path | None = None) -> AdapterReport:
    """``port``'s adapter with its latency timer set to 1 ms where permitted (`midas doctor`)."""
    return tune_latency_timer(find_adapter(port, root))


def prepare_port(port: str, fd: int | None, root: str | Path | None = None) -> AdapterReport:
    """What a driver calls once it opened ``port`` (file descriptor ``fd``, None if it has none): the
    adapter found, its latency timer set to 1 ms where permitted, the low-latency flag set. Logs a
    warning when the timer stays above 1 ms."""
    report = inspect_port(port, root)
    report.low_latency = set_low_latency(fd)
    if report.latency_timer_ms is not None and report.latency_timer_ms > WANTED_LATENCY_MS:
        log.warning("%s: %s", port, report.note)
    return report
