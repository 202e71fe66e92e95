"""``fob://PORT?baud=115200&sensors=4&rate=200&range=36``: the trakSTAR over its FOB-compatible RS-232 port.

Opening configures the tracker (optional RTS reset, FBB auto-configuration for N sensors, position
scaling, measurement rate, POSITION/ANGLES format per sensor, group mode), reads the settings back and
refuses a device that did not take them, then starts STREAM. Each measurement cycle becomes one row of
the EmHT stream layout (:mod:`~midas_cli.devices.emht_layout`, shared with ``sim://emht``):
``seq, t_host_ns, t_device_s`` (empty: the FOB records carry no device clock), per sensor x/y/z (mm),
azimuth/elevation/roll (deg) and quality (empty: not in POSITION/ANGLES records). A sensor whose record
failed framing has empty fields and is counted in ``counters.corrupt``; bytes thrown away by the decoder
are counted in ``counters.discarded_bytes``.

``t_host_ns`` is the host time of the read that completed the cycle's last record, less the line time of
the bytes that followed it in that read (see :class:`~midas_cli.devices.trakstar.protocol.RecordDecoder`),
and at least 1 ns after the previous row's (the session format wants strictly increasing host times).

``seq`` is the driver's cycle counter. On every (re)open it starts from the number of cycles the
session has lasted (session start to now at the nominal rate), never below where the previous
connection of this device (in the worker's context) stopped, so an outage shows as a sequence gap.
``PORT`` is anything pyserial's ``serial_for_url`` opens: ``/dev/ttyUSB0``, a pty path, a symlink.

The protocol has no checksum, so a record is accepted once the next record's first byte proves its end;
the last record of a burst (the tracker sends a cycle's group back to back, then nothing until the
next cycle) is accepted instead when the line has stayed idle after it for ``idle`` ms (default: 16
byte times at the baud rate, at least 0.5 ms; 0 = always wait for the next record). 16 byte times: a
16550-class UART hands the host a running transmission in FIFO-trigger chunks of up to 14 bytes, so
an extra byte sent right after a record reaches the host within that window; 0.5 ms covers the tty
layer's and the scheduler's delays. A USB-serial adapter holds bytes back up to its latency timer
(FTDI: 16 ms unless set lower): ``open`` sets it to 1 ms where permitted (:mod:`~midas_cli.devices.usbserial`,
recorded in the info as ``usb_serial``); else set it by hand, or ``idle`` above it. ``read`` never
blocks longer than 5 ms; the idle window is waited on the port's file descriptor (ports without one,
e.g. pyserial's ``socket://``, always wait for the next record).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import serial

from midas_cli.devices.base import Device, DeviceContext, DeviceUrl
from midas_cli.devices.emht_layout import emht_stream, first_seq, resume_seq
from midas_cli.devices.trakstar import protocol as fob
from midas_cli.devices.usbserial import prepare_port, read_available
from midas_cli.errors import ConfigError, DeviceError
from midas_cli.session.schema import StreamSpec

log = logging.getLogger(__name__)

PARAMS = {"baud": int, "sensors": int, "rate": float, "range": int, "reset": str, "timeout": float, "idle": float}
DEFAULTS = {"baud": 115200, "sensors": 4, "rate": 80.0, "range": 36, "reset": "none", "timeout": 1.0, "idle": None}
BAUDS = (9600, 19200, 38400, 57600, 115200)
READ_TIMEOUT_S = 0.005
IDLE_BYTES = 16  # line silence (byte times) that ends a burst: > a 16550 FIFO trigger level (14 bytes)
IDLE_FLOOR_S = 0.0005  # tty-layer and scheduling delay of a byte that was sent back to back
REPLY_TIMEOUT_S = 1.0
QUIET_S = 0.1  # the line counts as drained once no byte came for this long
DRAIN_MAX_S = 1.0  # a line that never goes quiet (a stream that did not stop) is drained this long at most
AUTOCONFIG_SETTLE_S = 0.6  # the Flock needs this long after an FBB auto-configuration
RTS_RESET_S = (1.0, 2.0)  # hold RTS high, then wait for the tracker to wake up



class SettingsMismatch(DeviceError):
    """The settings read back differ from those sent (said again after one more reading)."""

class FobEmHT(Device):
    """The trakSTAR (or any Flock-of-Birds-compatible tracker) on a serial port, group mode, STREAM."""

    kind = "emht"

    def __init__(self, name: str, url: DeviceUrl, context: DeviceContext) -> None:
        super().__init__(name, url)
        self.params = url.take(PARAMS, DEFAULTS)
        self.port_path = url.target
        self._validate()
        self.context = context
        self.clock = context.clock
        self._resume = resume_seq(context, name)
        self.capacity_hz = fob.line_capacity_hz(self.params["baud"], self.params["sensors"])
        self.warning = self._capacity_warning()
        self._port: serial.Serial | None = None
        self._byte_ns = int(fob.BITS_PER_BYTE_ON_WIRE * 1e9 / self.params["baud"])
        self.idle_s = self._idle_window_s()
        self._fd: int | None = None
        self._decoder = fob.RecordDecoder(self.params["sensors"], self.params["range"], self._byte_ns)
        self._groups = fob.GroupAssembler(self.params["sensors"])
        self._seq_base = 0
        self._last_data = 0.0
        self._last_t_host_ns = 0

    def _validate(self) -> None:
        p, raw = self.params, self.url.raw
        if not self.port_path:
            raise ConfigError(f"{raw}: no serial port (expected e.g. fob:///dev/ttyUSB0?baud=115200)")
        if p["baud"] not in BAUDS:
            raise ConfigError(f"{raw}: baud must be one of {', '.join(map(str, BAUDS))}, got {p['baud']}")
        if not 1 <= p["sensors"] <= 4:
            raise ConfigError(f"{raw}: sensors must be 1..4, got {p['sensors']}")
        if not 0 < p["rate"] <= fob.MAX_RATE_HZ:
            raise ConfigError(f"{raw}: rate must be in (0, {fob.MAX_RATE_HZ:.1f}] Hz, got {p['rate']}")
        if p["range"] not in fob.RANGES_IN:
            raise ConfigError(f"{raw}: range must be 36 or 72 (inches), got {p['range']}")
        if p["reset"] not in ("none", "rts"):
            raise ConfigError(f"{raw}: reset must be none or rts, got {p['reset']!r}")
        if p["timeout"] <= 0:
            raise ConfigError(f"{raw}: timeout must be positive, got {p['timeout']}")
        if p["idle"] is not None and not 0 <= p["idle"] < 1000 * p["timeout"]:
            raise ConfigError(f"{raw}: idle must be in [0, timeout) ms (0 = wait for the next record), got {p['idle']}")

    def _idle_window_s(self) -> float:
        """Line silence (s) after which a complete record at the end of a burst is accepted; 0 = never."""
        if self.params["idle"] is not None:
            return self.params["idle"] / 1000.0
        return max(IDLE_FLOOR_S, IDLE_BYTES * self._byte_ns / 1e9)

    def _capacity_warning(self) -> str:
        """A warning when rate x sensors x 13 bytes x 10 bits exceeds the baud rate, else ''."""
        p = self.params
        if p["rate"] <= self.capacity_hz:
            return ""
        text = (f"{self.name}: {p['rate']:g} Hz x {p['sensors']} sensors x {fob.RECORD_BYTES} bytes needs "
                f"{p['rate'] * p['sensors'] * fob.RECORD_BYTES * 10:.0f} baud but the line has {p['baud']}: "
                f"at most {self.capacity_hz:.1f} records/s per sensor fit; the tracker will skip measurements "
                f"(lower the rate or the number of sensors)")
        log.warning(text)
        return text

    @property
    def streams(self) -> list[StreamSpec]:
        return [emht_stream(self.name, self.params["sensors"], self.params["rate"],
                            "6-DoF pose per sensor from the trakSTAR's RS-232 (FOB) port, one row per cycle")]

    def settings(self) -> dict[str, Any]:
        extra = {"warning": self.warning} if self.warning else {}
        return {"protocol": "Flock of Birds RS-232, group mode, POSITION/ANGLES, STREAM", "port": self.port_path,
                **self.params, "idle": round(self.idle_s * 1000, 3),
                "line_capacity_hz_per_sensor": round(self.capacity_hz, 1), **extra}

    # -- opening ------------------------------------------------------------------------------------
    def open(self) -> dict[str, Any]:
        try:
            self._port = serial.serial_for_url(self.port_path, baudrate=self.params["baud"], timeout=READ_TIMEOUT_S,
                                               write_timeout=REPLY_TIMEOUT_S)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"{self.name}: cannot open serial port {self.port_path}: {exc} "
                              f"(is the trakSTAR connected and switched on, and is the port right?)") from exc
        self._fd = self._port_fd()
        adapter = prepare_port(self.port_path, self._fd)
        try:
            info = {**self._configure(), "usb_serial": adapter.as_dict()}
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise DeviceError(f"{self.name}: serial port {self.port_path} failed while configuring: {exc}") from exc
        except DeviceError:
            self.close()
            raise
        return info

    def _configure(self) -> dict[str, Any]:
        """Reset, configure, verify and start streaming; return what the device said about itself."""
        p = self.params
        self._stop_stream()
        if p["reset"] == "rts":
            self._rts_reset()
        self._send(fob.change_byte(fob.PARAM_AUTOCONFIG, p["sensors"]))
        time.sleep(AUTOCONFIG_SETTLE_S)
        self._send(fob.change_word(fob.PARAM_POSITION_SCALING, fob.RANGES_IN[p["range"]]))
        self._send(fob.change_word(fob.PARAM_MEASUREMENT_RATE, fob.rate_word(p["rate"])))
        for address in range(1, p["sensors"] + 1):
            self._send(fob.to_sensor(address) + fob.POSITION_ANGLES)
        self._send(fob.change_byte(fob.PARAM_GROUP_MODE, 1))
        info = self._verify()
        self._start_stream()
        return info

    def _verify(self) -> dict[str, Any]:
        try:
            return self._verify_once()
        except SettingsMismatch:  # a stray byte in front of an answer shifts every value: read them all again once
            log.warning("%s: the settings read back did not match; reading them again", self.name)
            self._drain_until_quiet()
            return self._verify_once()

    def _verify_once(self) -> dict[str, Any]:
        p = self.params
        rate_word = self._examine(fob.PARAM_MEASUREMENT_RATE)
        scaling = self._examine(fob.PARAM_POSITION_SCALING)
        group = self._examine(fob.PARAM_GROUP_MODE)
        sensors = self._examine(fob.PARAM_AUTOCONFIG)
        if rate_word != fob.rate_word(p["rate"]) or scaling != fob.RANGES_IN[p["range"]] or group != 1:
            raise SettingsMismatch(
                f"{self.name}: the tracker did not take the settings: measurement rate {rate_word / 256:g} Hz "
                f"(asked {p['rate']:g}), position scaling {scaling} (asked {fob.RANGES_IN[p['range']]}), "
                f"group mode {group} (asked 1); check the rate is supported by this tracker")
        if sensors != p["sensors"]:
            raise SettingsMismatch(f"{self.name}: the tracker runs {sensors} sensor(s), asked for {p['sensors']}: "
                              f"are {p['sensors']} sensors plugged in? (set sensors= in the URL to what is attached)")
        revision = self._examine(fob.PARAM_REVISION)
        serial_number = self._examine(fob.PARAM_SERIAL_NUMBER)
        return {"model": "trakSTAR / Flock of Birds (RS-232)", "serial": str(serial_number),
                "firmware": f"{revision & 0xFF}.{revision >> 8}", "measurement_rate_hz": rate_word / 256}

    def _rts_reset(self) -> None:
        hold_s, wake_s = RTS_RESET_S
        self._port.rts = True
        time.sleep(hold_s)
        self._port.rts = False
        time.sleep(wake_s)
        self._port.reset_input_buffer()

    def _stop_stream(self) -> None:
        """POINT stops a stream left running; drop whatever it and the stream sent, waiting until the
        line has been quiet for QUIET_S: the POINT answer itself may come late (a USB-serial adapter's
        latency timer, a busy host) and must not be read as the answer to the EXAMINEs that follow."""
        self._send(fob.POINT)
        self._drain_until_quiet()

    def _drain_until_quiet(self) -> None:
        deadline = time.monotonic() + DRAIN_MAX_S
        last_byte = time.monotonic()
        while time.monotonic() < deadline and time.monotonic() - last_byte < QUIET_S:
            if self._port.read(max(1, self._port.in_waiting)):
                last_byte = time.monotonic()
        self._port.reset_input_buffer()

    def _start_stream(self) -> None:
        self._port.reset_input_buffer()
        self._seq_base = first_seq(self.context, self.name, self.params["rate"])
        self._decoder = fob.RecordDecoder(self.params["sensors"], self.params["range"], self._byte_ns)
        self._groups = fob.GroupAssembler(self.params["sensors"])
        self._send(fob.STREAM)
        self._last_data = time.monotonic()

    def _port_fd(self) -> int | None:
        """The port's file descriptor to wait on for the idle window, None where pyserial has none."""
        try:
            return self._port.fileno()
        except (AttributeError, OSError, ValueError, serial.SerialException):
            return None

    def _send(self, command: bytes) -> None:
        self._port.write(command)
        self._port.flush()

    def _examine(self, param: int) -> int:
        self._send(fob.examine(param))
        wanted = fob.reply_length(param)
        reply = bytearray()
        deadline = time.monotonic() + REPLY_TIMEOUT_S
        while len(reply) < wanted and time.monotonic() < deadline:
            reply += self._port.read(wanted - len(reply))
        if len(reply) < wanted:
            raise DeviceError(f"{self.name}: no answer to EXAMINE VALUE {param} within {REPLY_TIMEOUT_S:g} s "
                              f"(got {len(reply)} of {wanted} bytes) on {self.port_path}: is the tracker on, "
                              f"in FOB/RS-232 mode and set to {self.params['baud']} baud?")
        return fob.parse_reply(param, bytes(reply))

    # -- streaming ----------------------------------------------------------------------------------
    def read(self) -> dict[str, list[tuple]]:
        """New rows (at most 5 ms blocking): the cycles completed by the bytes that arrived, or by the line
        staying idle after a burst (see the module docstring)."""
        if self._port is None:
            raise DeviceError(f"{self.name}: read before open")
        try:
            chunk = self._read_chunk()
        except (serial.SerialException, OSError) as exc:
            raise DeviceError(f"{self.name}: serial port {self.port_path} failed: {exc}") from exc
        now = time.monotonic()
        if chunk:
            self._last_data = now
            records = self._decoder.feed(chunk, self.clock.now_ns())
        elif self._idle_wait_s(now) == 0.0:
            records = self._decoder.accept_pending()
        elif now - self._last_data > self.params["timeout"]:
            raise DeviceError(f"{self.name}: no data from {self.port_path} for {self.params['timeout']:g} s")
        else:
            return {}
        groups = self._groups.add(records)
        self.counters.corrupt = self._groups.missing
        self.counters.discarded_bytes = self._decoder.counts.discarded_bytes
        return {self.name: [self._row(group) for group in groups]} if groups else {}

    def _read_chunk(self) -> bytes:
        """What arrived; b'' when nothing came within 5 ms, or (a record pending) within the idle window."""
        wait_s = self._idle_wait_s(time.monotonic())
        return read_available(self._port, self._fd, READ_TIMEOUT_S if wait_s is None else min(wait_s, READ_TIMEOUT_S))

    def _idle_wait_s(self, now: float) -> float | None:
        """Seconds of the idle window still to wait for the pending record (0.0: the line has been idle long
        enough, accept it); None when no record is pending or idle acceptance is off."""
        if not (self._decoder.pending and self.idle_s > 0 and self._fd is not None):
            return None
        return max(0.0, self._last_data + self.idle_s - now)

    def _row(self, group: fob.Group) -> tuple:
        seq = self._seq_base + group.index
        self._resume.next_seq = seq + 1
        self._last_t_host_ns = max(group.t_host_ns, self._last_t_host_ns + 1)
        values: list[Any] = []
        for sensor in group.values:
            values += list(sensor) + [None] if sensor is not None else [None] * 7
        return (seq, self._last_t_host_ns, None, *values)

    def close(self) -> None:
        if self._port is None:
            return
        try:
            self._send(fob.POINT)
        except (serial.SerialException, OSError):
            pass  # the port is already gone (unplugged); nothing to stop
        self._port.close()
        self._port = None
        self._fd = None
