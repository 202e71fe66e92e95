"""A byte-faithful trakSTAR emulator: the FOB RS-232 protocol served on a pseudo-terminal.

The tracker measures in cycles at its measurement rate (set by the host with CHANGE VALUE 7); cycle k
samples the simulated surgeon (:class:`~midas_cli.synthetic.surgeon.SurgeonMotion`) at model time
``t_k`` (seconds since the emulator started). In STREAM mode each cycle is sent as one group of
records (sensor 1..N, 13 bytes each), paced like a real 8N1 line: a cycle whose bytes would not fit
the line before the next one is due is skipped, as the tracker does. The host's FBB auto-configuration
(CHANGE VALUE 50, N) sets how many sensors the tracker answers and streams (1..the ``sensors`` attached;
all of them at power-on and after an unplug). Faults (all seeded) are the
:class:`~midas_cli.devices.pty_emulator.Faults` of every pty emulator; a corrupted byte here is line
noise that breaks framing (phasing bit inverted, data bits random). The pty, its ``link``, the serving
thread and the fault schedule are :class:`~midas_cli.devices.pty_emulator.PtyEmulator`'s.

``summary()`` reports exactly what was sent: the counters (and model times) of every cycle sent in
stream mode, per-sensor record counts, damaged records (counter, sensor), bytes corrupted/dropped,
the host's sensor count and unplug times (Unix ns), so a test can prove zero loss or find every corrupted record.
With ``send_log`` each cycle sent in stream mode is logged (``cycle``: its counter, as in
``stream_counters``; :mod:`~midas_cli.devices.send_log`) when the write of its group returned.
"""

from __future__ import annotations

import select
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from midas_cli.devices.pty_emulator import Faults, PtyEmulator
from midas_cli.devices.trakstar import protocol as fob
from midas_cli.errors import ConfigError
from midas_cli.synthetic.surgeon import MotionConfig, SurgeonMotion

POWER_ON_RATE_HZ = 80.0
REVISION = 3 | (67 << 8)  # firmware 3.67: the first byte sent is the major number, the second the minor
SERIAL_NUMBER = 4242
BLOCK_CYCLES = 64  # poses are computed this many cycles ahead (vectorised)


@dataclass(frozen=True)
class EmulatorConfig:
    """Tracker settings; ``sensors`` is how many are attached (the host may use fewer)."""

    sensors: int = 4
    baud: int = 115200
    seed: int = 0
    faults: Faults = Faults()
    link: str | None = None
    point_delay_s: float = 0.0  # answer POINT this late (a USB-serial adapter's latency timer, a busy host)
    send_log: str | None = None  # log each streamed cycle's send time here (devices/send_log.py)

    def __post_init__(self) -> None:
        if not 0.0 <= self.point_delay_s <= 5.0:
            raise ConfigError(f"point_delay_s must be in [0, 5] s, got {self.point_delay_s}")
        if not 1 <= self.sensors <= 4:
            raise ConfigError(f"sensors must be 1..4, got {self.sensors}")
        if self.baud <= 0:
            raise ConfigError(f"baud must be positive, got {self.baud}")


@dataclass
class _State:
    """What the host configured (reset by an unplug, like a power cycle)."""

    sensors: int
    rate_hz: float = POWER_ON_RATE_HZ
    scaling: int = 0
    group_mode: int = 0
    streaming: bool = False
    addressed: int = 1


@dataclass
class _Tally:
    stream_counters: list[int] = field(default_factory=list)
    stream_t_model_s: list[float] = field(default_factory=list)
    point_counters: list[int] = field(default_factory=list)
    records_per_sensor: list[int] = field(default_factory=list)
    damaged: list[tuple[int, int]] = field(default_factory=list)
    bytes_sent: int = 0
    bytes_lost_host_buffer: int = 0
    cycles_skipped_line_full: int = 0
    cycles_skipped_stall: int = 0
    commands: dict[str, int] = field(default_factory=dict)


class TrakstarEmulator(PtyEmulator):
    """Serve the FOB protocol on a pty from a thread (``start``/``stop``) or the caller's thread (``serve``)."""

    label = "trakSTAR"
    send_log_identity = ("cycle",)

    def __init__(self, config: EmulatorConfig) -> None:
        super().__init__(config.faults, config.link, config.seed, config.send_log)
        self.config = config
        self.motion = SurgeonMotion(MotionConfig(seed=config.seed))
        self._state = _State(config.sensors)
        self._tally = _Tally(records_per_sensor=[0] * config.sensors)
        self._commands = bytearray()
        self._cycle = 0
        self._block_range = 36
        self._point_due: float | None = None  # when a delayed POINT answer goes out
        self._plug()  # the path is known (and printed) before serving starts

    def _summary(self) -> dict[str, Any]:
        tally = asdict(self._tally)
        tally["damaged"] = [list(d) for d in tally["damaged"]]
        return {"config": asdict(self.config), "sensors": self._state.sensors, "rate_hz": self._state.rate_hz,
                "range_in": 72 if self._state.scaling else 36,
                "stream_groups_sent": len(tally["stream_counters"]), **tally}

    def expected_values(self, t_model_s: np.ndarray, range_in: int) -> np.ndarray:
        """Decoded values (N, sensors, 6) a host must see for cycles at model times ``t_model_s``."""
        return fob.values_from_words(self._words(np.asarray(t_model_s, dtype=np.float64), range_in), range_in)

    # -- the loop -----------------------------------------------------------------------------------
    def _step(self, now: float) -> None:
        """Answer commands, emit due cycles."""
        timeout = min(0.01, max(0.0, self._next_due - now))
        readable, _, _ = select.select([self.port.master], [], [], timeout)
        if readable:
            self._receive()
        if self._point_due is not None and time.monotonic() >= self._point_due:
            self._point_due = None
            self._send_cycle(self._cycle - 1, self._cycle_time(self._cycle - 1), point=True)
        self._emit_due_cycles(time.monotonic())

    def _on_plug(self, now: float) -> None:
        self._restart_cycles(now)

    def _on_unplug(self) -> None:
        self._commands.clear()
        self._state = _State(self.config.sensors)

    def _receive(self) -> None:
        data = self._read()
        if not data:  # no reader has the pty open (EIO): nothing to answer
            time.sleep(0.005)
            return
        self._commands += data
        while self._commands and self._handle_command():
            pass

    def _handle_command(self) -> bool:
        """Execute the command at the start of the buffer; False when it is still incomplete."""
        code = self._commands[0]
        if code == fob.EXAMINE[0] or code == fob.CHANGE[0]:
            return self._handle_value_command(code)
        del self._commands[:1]
        state = self._state
        if 0xF1 <= code <= 0xFE:
            address = code - fob.RS232_TO_FBB
            if 1 <= address <= state.sensors:  # a sensor that is not there (or not configured): no one answers
                state.addressed = address
            return True
        name = {ord("B"): "point", ord("@"): "stream", ord("Y"): "position_angles", ord("/"): "fbb_reset",
                ord("G"): "sleep", ord("F"): "run"}.get(code, f"unsupported_0x{code:02x}")
        self._count(name)
        if name == "point":
            state.streaming = False
            if self.config.point_delay_s:
                self._point_due = time.monotonic() + self.config.point_delay_s
            else:
                self._send_cycle(self._cycle - 1, self._cycle_time(self._cycle - 1), point=True)
        elif name == "stream":
            state.streaming = True
        elif name in ("fbb_reset", "sleep"):
            state.streaming = False
            state.group_mode = 0 if name == "fbb_reset" else state.group_mode
        state.addressed = 1
        return True

    def _handle_value_command(self, code: int) -> bool:
        if len(self._commands) < 2:
            return False
        param = self._commands[1]
        try:
            length = fob.reply_length(param)
        except ValueError:
            self._count(f"unsupported_parameter_{param}")
            del self._commands[:2]
            return True
        if code == fob.EXAMINE[0]:
            del self._commands[:2]
            self._count(f"examine_{param}")
            self._send(self._parameter(param).to_bytes(length, "little"))
            return True
        if len(self._commands) < 2 + length:
            return False
        value = int.from_bytes(self._commands[2:2 + length], "little")
        del self._commands[:2 + length]
        self._count(f"change_{param}")
        self._change(param, value)
        return True

    def _parameter(self, param: int) -> int:
        state = self._state
        return {fob.PARAM_REVISION: REVISION, fob.PARAM_POSITION_SCALING: state.scaling,
                fob.PARAM_MEASUREMENT_RATE: fob.rate_word(state.rate_hz), fob.PARAM_SERIAL_NUMBER: SERIAL_NUMBER,
                fob.PARAM_GROUP_MODE: state.group_mode, fob.PARAM_AUTOCONFIG: state.sensors}[param]

    def _change(self, param: int, value: int) -> None:
        state = self._state
        state.streaming = False
        if param == fob.PARAM_MEASUREMENT_RATE and value > 0:
            state.rate_hz = value / 256.0
            self._restart_cycles(time.monotonic())
        elif param == fob.PARAM_POSITION_SCALING and value in (0, 1):
            state.scaling = value
        elif param == fob.PARAM_GROUP_MODE:
            state.group_mode = 1 if value else 0
        elif param == fob.PARAM_AUTOCONFIG and 1 <= value <= self.config.sensors:
            state.sensors = value  # FBB auto-configuration: answer and stream only these sensors
            state.addressed = min(state.addressed, value)

    def _count(self, name: str) -> None:
        self._tally.commands[name] = self._tally.commands.get(name, 0) + 1

    # -- cycles -------------------------------------------------------------------------------------
    def _restart_cycles(self, now: float) -> None:
        """A new measurement rate: cycles continue counting, timed from now."""
        self._phase = (self._cycle, now)
        self._next_due = now + 1.0 / self._state.rate_hz
        self._line_free_at = now
        self._block: tuple[int, np.ndarray] = (-1, np.empty((0, self.config.sensors, 6), dtype=np.int16))

    def _cycle_time(self, k: int) -> float:
        """Model time (s since the emulator started) of cycle k, rounded to microseconds."""
        k0, t0 = self._phase
        return round(t0 - self._t0 + (k - k0) / self._state.rate_hz, 6)

    def _emit_due_cycles(self, now: float) -> None:
        period = 1.0 / self._state.rate_hz
        line_time = self._state.sensors * fob.RECORD_BYTES * fob.BITS_PER_BYTE_ON_WIRE / self.config.baud
        while self._next_due <= now and self.port.plugged:
            due = self._next_due
            k = self._cycle
            self._cycle += 1
            self._next_due += period
            if not self._state.streaming:
                continue
            if self._stalled(due):
                self._tally.cycles_skipped_stall += 1
                continue
            if max(self._line_free_at, due) + line_time > due + period:
                self._tally.cycles_skipped_line_full += 1
                continue
            self._line_free_at = max(self._line_free_at, due) + line_time
            self._send_cycle(k, self._cycle_time(k), point=False)

    def _send_cycle(self, k: int, t_model: float, point: bool) -> None:
        range_in = 72 if self._state.scaling else 36
        words = self._cycle_words(k, t_model, range_in)
        group = self._state.group_mode == 1
        sensors = range(1, self._state.sensors + 1) if group else (self._state.addressed,)
        records = [fob.encode_record(words[s - 1], s if group else None) for s in sensors]
        wire, damaged = self._apply_line_faults(records)
        if self._send(wire):
            tally = self._tally
            (tally.point_counters if point else tally.stream_counters).append(k)
            if not point:
                tally.stream_t_model_s.append(t_model)
                if self.send_log is not None:
                    self.send_log.record((k,), self._t0 + t_model, self.last_write_ns)
            for s in sensors:
                tally.records_per_sensor[s - 1] += 1
            tally.damaged += [(k, list(sensors)[i]) for i in damaged]

    def _cycle_words(self, k: int, t_model: float, range_in: int) -> np.ndarray:
        """Words (sensors, 6) of cycle k, from a block computed ahead."""
        start, block = self._block
        if not start <= k < start + len(block) or self._block_range != range_in:
            times = np.array([self._cycle_time(j) for j in range(k, k + BLOCK_CYCLES)])
            self._block = (k, self._words(np.maximum(times, 0.0), range_in))
            self._block_range = range_in
            start, block = self._block
        return block[k - start]

    def _words(self, t: np.ndarray, range_in: int) -> np.ndarray:
        positions, angles = self.motion.sensor_poses(t)  # (N, 4, 3) mm, (N, 4, 3) deg
        values = np.concatenate([positions, angles], axis=2)[:, : self.config.sensors]  # (N, sensors, 6)
        return fob.words_from_values(values, range_in)

    def _apply_line_faults(self, records: list[bytes]) -> tuple[bytes, list[int]]:
        """Corrupt/drop bytes of ``records``; return the wire bytes and indexes of damaged records."""
        wire, damaged = bytearray(), []
        for index, record in enumerate(records):
            sent = self._damage(record)
            if sent != record:
                damaged.append(index)
            wire += sent
        return bytes(wire), damaged

    def _noise(self, raw: np.ndarray) -> np.ndarray:
        """Line noise that breaks framing: the phasing bit inverted, the data bits random."""
        phasing = np.where(raw & 0x80, 0, 0x80).astype(np.uint8)
        return self._rng.integers(0, 128, len(raw), dtype=np.uint8) | phasing

    def _send(self, data: bytes) -> bool:
        """Write to the pty; bytes the host's buffer cannot take are lost (counted). True if all went."""
        written = self._write(data)
        if written < 0:
            return False
        self._tally.bytes_sent += written
        self._tally.bytes_lost_host_buffer += len(data) - written
        return written == len(data)
