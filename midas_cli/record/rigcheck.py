"""Pre-flight check of a rig (``midas rig check``): open every device, read for a few seconds, close.

Each device is built exactly as a recording builds it (``devices/registry.create_device`` with a
``DeviceContext``), opened, read for ``seconds`` and closed, all devices at once (one thread each), and
its samples counted per stream against the stream's nominal rate. Nothing is written: no session
folder, no stream file. Backends that only work inside a session folder (``obs://`` points OBS's
recording into it, ``raven://`` keeps raw packets there) are listed as ``skipped`` with the reason;
`midas doctor` checks that OBS is reachable.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any

from midas_cli.clock import HostClock
from midas_cli.devices.base import DeviceContext, DeviceUrl
from midas_cli.devices.registry import create_device
from midas_cli.devices.rigconfig import RigConfig
from midas_cli.devices.usbserial import AdapterReport
from midas_cli.errors import ConfigError, DeviceError, MidasError

NEEDS_SESSION = {"obs": "obs:// records into a session folder (check OBS with `midas doctor`)",
                 "raven": "raven:// keeps raw packets in a session folder"}
STALL_S = 2.0  # a device that opened but sends nothing for this long is failed


@dataclass
class StreamCheck:
    samples: int = 0
    first_ns: int | None = None
    last_ns: int | None = None
    nominal_hz: float | None = None

    def measured_hz(self, seconds: float) -> float:
        if self.samples >= 2 and self.first_ns is not None and self.last_ns is not None and self.last_ns > self.first_ns:
            return (self.samples - 1) / ((self.last_ns - self.first_ns) / 1e9)
        return self.samples / seconds if seconds > 0 else 0.0


@dataclass
class DeviceCheck:
    """One device's result: ``state`` ok / failed / skipped, its streams' counts, the error if any."""

    device: str
    url: str
    state: str = "ok"
    error: str | None = None
    info: dict[str, Any] = field(default_factory=dict)
    open_s: float | None = None
    read_s: float = 0.0
    streams: dict[str, StreamCheck] = field(default_factory=dict)

    def serial_line(self) -> str:
        """What was in force on the device's serial port (adapter, latency timer, low-latency flag), '' for
        devices without one."""
        report = self.info.get("usb_serial")
        return AdapterReport(**report).summary() if isinstance(report, dict) else ""

    def as_dict(self) -> dict[str, Any]:
        return {"device": self.device, "url": self.url, "state": self.state, "error": self.error,
                "open_s": None if self.open_s is None else round(self.open_s, 3), "read_s": round(self.read_s, 3),
                "info": self.info,
                "streams": {name: {"samples": s.samples, "nominal_hz": s.nominal_hz,
                                   "measured_hz": round(s.measured_hz(self.read_s), 2)}
                            for name, s in self.streams.items()}}


def check_rig(config: RigConfig, seconds: float = 3.0, seed: int = 0) -> list[DeviceCheck]:
    """Open, read and close every device of ``config`` (concurrently); ConfigError (before any device is
    opened) for a URL no backend accepts."""
    if not seconds > 0:
        raise ConfigError(f"--seconds must be above 0, got {seconds}")
    clock = HostClock.anchored_now()
    urls = config.device_urls()
    for name, url in urls.items():  # every URL checked before anything is opened, as `midas record` does
        create_device(name, url, DeviceContext.describing(seed))
    results = {name: DeviceCheck(name, DeviceUrl.parse(url).redacted()) for name, url in urls.items()}
    threads = [threading.Thread(target=_check_one, args=(results[name], url, seconds, clock, seed), daemon=True,
                                name=f"rig-check-{name}") for name, url in urls.items()]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return list(results.values())


def _check_one(result: DeviceCheck, url: str, seconds: float, clock: HostClock, seed: int) -> None:
    scheme = DeviceUrl.parse(url).scheme
    if scheme in NEEDS_SESSION:
        result.state, result.error = "skipped", NEEDS_SESSION[scheme]
        return
    device = None
    try:
        device = create_device(result.device, url, DeviceContext(clock, clock.now_ns(), seed, ""))
        result.streams = {spec.name: StreamCheck(nominal_hz=spec.nominal_rate_hz) for spec in device.streams}
        started = time.monotonic()
        result.info = _plain(device.open())
        result.open_s = time.monotonic() - started
        _read(device, result, seconds)
    except Exception as exc:  # a device check reports every failure as that device's, never crashes the table
        result.state, result.error = "failed", _message(exc)
    finally:
        if device is not None:
            try:
                device.close()
            except Exception as exc:  # noqa: BLE001 - reported, the other devices still close
                if result.error is None:
                    result.state, result.error = "failed", f"close: {_message(exc)}"
    if result.state == "ok":
        silent = [name for name, s in result.streams.items() if s.nominal_hz and s.samples == 0]
        if silent:
            result.state = "failed"
            result.error = f"no samples in {result.read_s:.1f} s on {', '.join(silent)}"


def _read(device, result: DeviceCheck, seconds: float) -> None:
    started = time.monotonic()
    last_data = started
    try:
        while (now := time.monotonic()) - started < seconds:
            rows_by_stream = device.read()
            for name, rows in rows_by_stream.items():
                if not rows:
                    continue
                stream = result.streams.setdefault(name, StreamCheck())
                stream.samples += len(rows)
                stream.first_ns = int(rows[0][1]) if stream.first_ns is None else stream.first_ns
                stream.last_ns = int(rows[-1][1])
                last_data = now
            if now - last_data > STALL_S:
                raise DeviceError(f"{result.device}: no data for {STALL_S:.1f} s")
    finally:
        result.read_s = time.monotonic() - started


def _message(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if isinstance(exc, MidasError) and text else f"{type(exc).__name__}: {text}".rstrip(": ")


def _plain(info: Any) -> dict[str, Any]:
    """``info`` with JSON-plain values: scalars as they are, dicts (e.g. ``usb_serial``) made plain in turn,
    anything else as text."""
    return {str(k): (v if isinstance(v, (str, int, float, bool, type(None))) else _plain(v) if isinstance(v, dict)
                     else str(v)) for k, v in (info or {}).items()} if isinstance(info, dict) else {}
