"""The FPS pedal board over USB serial: ``fps://PORT?baud=500000&rate=250&channels=9&press_v=…&release_v=…``.

PORT is anything pyserial's ``serial_for_url`` opens: ``/dev/ttyACM0``, a pty such as ``/dev/pts/5``
(the emulator), or a symlink to one. Handshake: ``ID`` (answered by the banner), ``RATE``, ``START``;
on close ``STOP``. Every sample row is ``seq, t_host_ns, t_device_us, ch1_adc.., ch1_pressed..`` (the
same layout as ``sim://fps``): ``seq`` is the board's counter, ``t_host_ns`` the host clock when the read
that completed the line returned (taken before the bytes are decoded, so a batch that arrived together
is not stamped later by its own decoding), ``t_device_us`` the board's micros() (wraps at 2^32), pressed states from the thresholds with
hysteresis (``press_v``/``release_v``: one value for every channel or a comma list, one per channel).

The board restarts its counter when it reboots (an Uno resets whenever its port is opened). So that a
session's ``seq`` never goes backwards, a restart mid-session is continued from the last sequence
number plus the samples the outage lasted (at the nominal rate); the offset is logged and counted in
``counters.extra["seq_rebased"]``. Without a restart ``seq`` is the board's number, unchanged.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import serial

from midas_cli.devices.base import Device, DeviceContext, DeviceUrl
from midas_cli.devices.fps.protocol import (
    MAX_RATE_HZ, PROTO_VERSION, Banner, LineDecoder, Message, Reply, Sample, encode_command, max_rate_hz, rate_fits,
)
from midas_cli.devices.pedals import PedalStateTracker, PedalThresholds
from midas_cli.devices.usbserial import port_fd, prepare_port, read_available
from midas_cli.errors import ConfigError, DeviceError
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec

log = logging.getLogger(__name__)

DEFAULT_BAUD = 500_000
READ_TIMEOUT_S = 0.005
RESEND_EVERY_S = 0.5


def volt_list(text: str) -> tuple[float, ...]:
    """URL value ``1.5`` or ``1.5,1.2,…`` -> volts per channel (ValueError if not numbers)."""
    return tuple(float(part) for part in text.split(","))


ALLOWED = {"baud": int, "rate": int, "channels": int, "press_v": volt_list, "release_v": volt_list,
           "timeout": float}
DEFAULTS = {"baud": DEFAULT_BAUD, "rate": 250, "channels": 9, "press_v": (1.5,), "release_v": (1.0,),
            "timeout": 3.0}


def fps_stream_spec(name: str, channels: int, rate_hz: float) -> StreamSpec:
    """The pedal stream: seq, t_host_ns, t_device_us, ch{k}_adc, ch{k}_pressed (as ``sim://fps``)."""
    columns = [SEQ, T_HOST, Column("t_device_us", "int", "us", clock="device", description="board micros(), wraps at 2^32")]
    columns += [Column(f"ch{c}_adc", "int", "counts", description="10-bit ADC, Vcc 5 V") for c in range(1, channels + 1)]
    columns += [Column(f"ch{c}_pressed", "int", "bool", description="press state, thresholds with hysteresis")
                for c in range(1, channels + 1)]
    return StreamSpec(name, name, tuple(columns), rate_hz, "foot pedal FSR voltages and states")


def thresholds_from_params(params: dict[str, Any], url: str) -> PedalThresholds:
    """Per-channel thresholds from the URL's press_v/release_v (a single value applies to all)."""
    n = params["channels"]
    lists = []
    for key in ("press_v", "release_v"):
        values = params[key]
        if len(values) not in (1, n):
            raise ConfigError(f"{url}: {key} needs 1 or {n} comma-separated values (one per channel), got {len(values)}")
        lists.append(tuple(values) * n if len(values) == 1 else tuple(values))
    return PedalThresholds(lists[0], lists[1])


@dataclass
class _SeqState:
    """What a worker remembers across reconnects of one device in one session (see module docstring)."""

    offset: int = 0
    last_out: int | None = None
    last_t_host_ns: int = 0


class FpsDevice(Device):
    """The MIDAS-FPS firmware (or its emulator) on a serial port."""

    kind = "fps"

    def __init__(self, name: str, url: DeviceUrl, context: DeviceContext) -> None:
        super().__init__(name, url)
        self.params = url.take(ALLOWED, DEFAULTS)
        self.port = url.target
        self._validate()
        self.thresholds = thresholds_from_params(self.params, url.raw)
        self.clock = context.clock
        self.state = context.carry(f"{name}/fps-seq", _SeqState)
        self.tracker = PedalStateTracker(self.thresholds)
        self.decoder = LineDecoder()
        self._serial: serial.SerialBase | None = None
        self._fd: int | None = None  # the port's descriptor (read_available), None for loop:// and the like
        self._read_ns = 0  # host time when the last read returned
        self.counters.extra["seq_rebased"] = 0

    def _validate(self) -> None:
        p, raw = self.params, self.url.raw
        if not self.port:
            raise ConfigError(f"{raw}: no serial port (expected e.g. fps:///dev/ttyACM0)")
        if not 1 <= p["channels"] <= 9:
            raise ConfigError(f"{raw}: channels must be 1..9, got {p['channels']}")
        if p["timeout"] <= 0:
            raise ConfigError(f"{raw}: timeout must be positive seconds, got {p['timeout']}")
        if not 1 <= p["rate"] <= MAX_RATE_HZ:
            raise ConfigError(f"{raw}: rate must be 1..{MAX_RATE_HZ} Hz, got {p['rate']}")

    @property
    def streams(self) -> list[StreamSpec]:
        return [fps_stream_spec(self.name, self.params["channels"], float(self.params["rate"]))]

    def settings(self) -> dict[str, Any]:
        p = self.params
        return {"port": self.port, "baud": p["baud"], "rate": p["rate"], "channels": p["channels"],
                "press_v": list(self.thresholds.press_v), "release_v": list(self.thresholds.release_v)}

    # ---- connection --------------------------------------------------------------------------------

    def open(self) -> dict[str, Any]:
        try:
            self._serial = serial.serial_for_url(self.port, baudrate=self.params["baud"], timeout=READ_TIMEOUT_S,
                                                 write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"{self.name}: cannot open {self.port}: {exc} (is the board plugged in?)") from exc
        self._fd = port_fd(self._serial)
        adapter = prepare_port(self.port, self._fd)
        try:
            return {**self._handshake(), "usb_serial": adapter.as_dict()}
        except DeviceError:
            self.close()
            raise

    def _handshake(self) -> dict[str, Any]:
        self._serial.reset_input_buffer()
        banner = self._request(encode_command("ID"), lambda m: isinstance(m, Banner))
        self._check_banner(banner)
        self.decoder.channels = banner.channels
        self._request(encode_command("RATE", self.params["rate"]), lambda m: _is_reply(m, "RATE"))
        self._request(encode_command("START"), lambda m: _is_reply(m, "START"))
        log.info("%s: %s firmware %s streaming at %d Hz", self.name, self.port, banner.fw, self.params["rate"])
        return {"model": "MIDAS-FPS pedal board", "firmware": banner.fw, "protocol": banner.proto,
                "mcu": banner.fields.get("mcu", ""), "board_channels": banner.channels, "port": self.port}

    def _check_banner(self, banner: Banner) -> None:
        if banner.proto != PROTO_VERSION:
            raise DeviceError(f"{self.name}: the board speaks MIDAS-FPS protocol {banner.proto}, this midas speaks "
                              f"{PROTO_VERSION}: update the firmware (firmware/fps) or midas")
        if banner.channels < self.params["channels"]:
            raise DeviceError(f"{self.name}: the board has {banner.channels} channels, the URL asks for "
                              f"{self.params['channels']}: set channels={banner.channels} or fewer")
        baud = int(banner.fields.get("baud", self.params["baud"]))
        if not rate_fits(self.params["rate"], banner.channels, baud):
            raise DeviceError(
                f"{self.name}: rate={self.params['rate']} Hz does not fit the board ({banner.channels} channels "
                f"at {baud} baud: at most {max_rate_hz(banner.channels, baud)} Hz); lower the rate or build the "
                "firmware for fewer CHANNELS or a higher BAUD")

    def _request(self, command: bytes, wanted) -> Message:
        """Send ``command`` (again every 0.5 s) until a wanted message arrives; DeviceError on timeout or ERR."""
        deadline = time.monotonic() + self.params["timeout"]
        next_send = 0.0
        while time.monotonic() < deadline:
            if time.monotonic() >= next_send:
                self._write(command)
                next_send = time.monotonic() + RESEND_EVERY_S
            for message in self._receive():
                if wanted(message):
                    return message
                if isinstance(message, Reply) and not message.ok:
                    raise DeviceError(f"{self.name}: the board refused {command.split(b'*')[0].decode()!r}: "
                                      f"ERR {message.what}")
        raise DeviceError(f"{self.name}: no answer to {command.split(b'*')[0].decode()!r} from {self.port} within "
                          f"{self.params['timeout']:g} s (wrong port or baud, or not MIDAS-FPS firmware?)")

    def _write(self, data: bytes) -> None:
        try:
            self._serial.write(data)
        except (serial.SerialException, OSError) as exc:
            raise DeviceError(f"{self.name}: writing to {self.port} failed: {exc}") from exc

    def _receive(self) -> list[Message]:
        try:
            data = read_available(self._serial, self._fd, READ_TIMEOUT_S)
            if data:  # woken by a line's first byte: take the rest in this pass
                data += read_available(self._serial, self._fd, 0.0)
            self._read_ns = self.clock.now_ns()
        except (serial.SerialException, OSError) as exc:
            raise DeviceError(f"{self.name}: lost {self.port}: {exc}") from exc
        messages = self.decoder.feed(data) if data else []
        self.counters.corrupt = self.decoder.corrupt_lines
        self.counters.discarded_bytes = self.decoder.discarded_bytes
        return messages

    def pause(self) -> None:
        """Stop streaming but keep the port (samples already on the wire are dropped by :meth:`restart`)."""
        self._write(encode_command("STOP"))

    def restart(self) -> None:
        """Start streaming again; every sample sent before the board acknowledged START is discarded."""
        self._request(encode_command("START"), lambda m: _is_reply(m, "START"))

    def close(self) -> None:
        port, self._serial, self._fd = self._serial, None, None
        if port is None:
            return
        try:
            port.write(encode_command("STOP"))
            port.flush()
        except (serial.SerialException, OSError):
            pass  # the board is gone already; nothing to stop
        finally:
            port.close()

    # ---- streaming ---------------------------------------------------------------------------------

    def read(self) -> dict[str, list[tuple]]:
        if self._serial is None:
            raise DeviceError(f"{self.name}: read before open")
        rows = [self._row(m) for m in self._receive() if isinstance(m, Sample)]
        return {self.name: rows} if rows else {}

    def _row(self, sample: Sample) -> tuple:
        t_host = max(self._read_ns, self.state.last_t_host_ns + 1)
        seq = self._session_seq(sample.seq, t_host)
        n = self.params["channels"]
        counts = sample.adc[:n]
        pressed = self.tracker.update_counts(counts)
        self.state.last_out, self.state.last_t_host_ns = seq, t_host
        return (seq, t_host, sample.t_us, *counts, *pressed)

    def _session_seq(self, board_seq: int, t_host: int) -> int:
        state = self.state
        seq = board_seq + state.offset
        if state.last_out is not None and seq <= state.last_out:
            missed = max(1, round((t_host - state.last_t_host_ns) / 1e9 * self.params["rate"]))
            state.offset = state.last_out + missed - board_seq
            seq = board_seq + state.offset
            self.counters.extra["seq_rebased"] += 1
            log.warning("%s: the board restarted its counter (board seq %d, session seq was %d): continuing at %d",
                        self.name, board_seq, state.last_out, seq)
        return seq


def _is_reply(message: Message, what: str) -> bool:
    return isinstance(message, Reply) and message.ok and message.what == what
