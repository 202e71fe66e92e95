"""A byte-faithful trakSTAR emulator: the FOB RS-232 protocol served on a pseudo-terminal.

The tracker measures in cycles at its measurement rate (set by the host with CHANGE VALUE 7); cycle k
samples the simulated surgeon (:class:`~midas_cli.synthetic.surgeon.SurgeonMotion`) at model time
``t_k`` (seconds since the emulator started). In STREAM mode each cycle is sent as one group of
records (sensor 1..N, 13 bytes each), paced like a real 8N1 line: a cycle whose bytes would not fit
the line before the next one is due is skipped, as the tracker does. Faults (all seeded): ``corrupt``
= probability per byte of line noise that breaks framing (phasing bit inverted, data bits random),
``drop`` = probability per byte of losing it, ``stall`` = no output for a while, ``unplug`` = the pty
is closed and reopened later. A pty cannot keep its /dev/pts number across a close, so ``link`` names
a symlink that always points at the current pty: open the link, not the pty.

``summary()`` reports exactly what was sent: the counters (and model times) of every cycle sent in
stream mode, per-sensor record counts, damaged records (counter, sensor), bytes corrupted/dropped,
and unplug times (Unix ns), so a test can prove zero loss or find every corrupted record.
"""

from __future__ import annotations

import json
import logging
import os
import select
import threading
import time
import tty
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.synthetic.surgeon import MotionConfig, SurgeonMotion
from midas_cli.devices.trakstar import protocol as fob
from midas_cli.errors import ConfigError, DeviceError

log = logging.getLogger(__name__)

POWER_ON_RATE_HZ = 80.0
REVISION = 3 | (67 << 8)  # firmware 3.67: the first byte sent is the major number, the second the minor
SERIAL_NUMBER = 4242
BLOCK_CYCLES = 64  # poses are computed this many cycles ahead (vectorised)


@dataclass
class EmulatorConfig:
    """Emulator settings; times in seconds since the emulator started, probabilities per byte."""

    sensors: int = 4
    baud: int = 115200
    seed: int = 0
    corrupt: float = 0.0
    drop: float = 0.0
    stall_at: float = -1.0
    stall_for: float = 0.0
    unplug_at: float = -1.0
    unplug_for: float = 0.0
    link: str | None = None

    def validate(self) -> None:
        if not 1 <= self.sensors <= 4:
            raise ConfigError(f"sensors must be 1..4, got {self.sensors}")
        if self.baud <= 0:
            raise ConfigError(f"baud must be positive, got {self.baud}")
        for name in ("corrupt", "drop"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ConfigError(f"{name} must be a probability in [0, 1), got {getattr(self, name)}")
        if self.unplug_at >= 0 and not self.link:
            raise ConfigError("an unplug changes the pty's path: give a link path that follows it")


@dataclass
class _State:
    """What the host configured (reset by an unplug, like a power cycle)."""

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
    bytes_corrupted: int = 0
    bytes_dropped: int = 0
    bytes_lost_host_buffer: int = 0
    cycles_skipped_line_full: int = 0
    cycles_skipped_stall: int = 0
    commands: dict[str, int] = field(default_factory=dict)
    unplugs: list[dict[str, Any]] = field(default_factory=list)


class TrakstarEmulator:
    """Serve the FOB protocol on a pty from a thread (``start``/``stop``) or the caller's thread (``serve``)."""

    def __init__(self, config: EmulatorConfig) -> None:
        config.validate()
        self.config = config
        self.motion = SurgeonMotion(MotionConfig(seed=config.seed))
        self._rng = np.random.default_rng(config.seed)
        self._state = _State()
        self._tally = _Tally(records_per_sensor=[0] * config.sensors)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = time.monotonic()
        self._stall_until = 0.0
        self._unplug_until = 0.0
        self._pending_unplug_s: float | None = None
        self._final_summary: dict[str, Any] | None = None
        self._scheduled_faults_done: set[str] = set()
        self._commands = bytearray()
        self._cycle = 0
        self._block_range = 36
        self._master = self._slave = -1
        self.pty_path = ""
        self._plug_in()
        self._restart_cycles(self._t0)

    # -- public API ---------------------------------------------------------------------------------
    @property
    def path(self) -> str:
        """The path a host opens: the link when configured, else the pty itself."""
        return self.config.link or self.pty_path

    def start(self) -> "TrakstarEmulator":
        self._thread = threading.Thread(target=self.serve, name="trakstar-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> dict[str, Any]:
        """Stop serving, close the pty, remove the link; return the summary."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._final_summary = self.summary()
        self._unplug_fds()
        if self.config.link and os.path.islink(self.config.link):
            os.unlink(self.config.link)
        return self.summary()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def stall(self, for_s: float) -> None:
        """Send nothing for ``for_s`` seconds (the cycles in between are skipped)."""
        self._stall_until = time.monotonic() + for_s

    def unplug(self, for_s: float) -> None:
        """Close the pty (within ~10 ms, by the serving thread) and reopen it at the link after ``for_s`` s."""
        if not self.config.link:
            raise ConfigError("an unplug changes the pty's path: give the emulator a link path that follows it")
        self._pending_unplug_s = for_s

    def _do_unplug(self, for_s: float) -> None:
        with self._lock:
            self._unplug_fds()
            self._unplug_until = time.monotonic() + for_s
            self._tally.unplugs.append({"unplugged_ns": time.time_ns(), "replugged_ns": None, "path": None})

    def summary(self) -> dict[str, Any]:
        """Exactly what was sent (see the module docstring)."""
        if self._final_summary is not None:
            return self._final_summary
        with self._lock:
            tally = asdict(self._tally)
        tally["damaged"] = [list(d) for d in tally["damaged"]]
        return {"config": asdict(self.config), "path": self.path, "pty": self.pty_path,
                "rate_hz": self._state.rate_hz, "range_in": 72 if self._state.scaling else 36,
                "stream_groups_sent": len(tally["stream_counters"]), **tally}

    def write_summary(self, path: Path | str) -> None:
        Path(path).write_text(json.dumps(self.summary()) + "\n", encoding="utf-8")

    def expected_values(self, t_model_s: np.ndarray, range_in: int) -> np.ndarray:
        """Decoded values (N, sensors, 6) a host must see for cycles at model times ``t_model_s``."""
        return fob.values_from_words(self._words(np.asarray(t_model_s, dtype=np.float64), range_in), range_in)

    # -- the loop -----------------------------------------------------------------------------------
    def serve(self) -> None:
        """Run until ``stop()``: answer commands, emit due cycles, apply scheduled faults."""
        while not self._stop.is_set():
            now = time.monotonic()
            self._scheduled_faults(now)
            if self._pending_unplug_s is not None:
                self._do_unplug(self._pending_unplug_s)
                self._pending_unplug_s = None
            if self._master < 0:
                self._maybe_replug(now)
                time.sleep(0.01)
                continue
            timeout = min(0.01, max(0.0, self._next_due - now))
            readable, _, _ = select.select([self._master], [], [], timeout)
            if readable:
                self._receive()
            self._emit_due_cycles(time.monotonic())

    def _receive(self) -> None:
        try:
            data = os.read(self._master, 4096)
        except OSError:  # no reader has the pty open (EIO): nothing to answer
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
            state.addressed = code - fob.RS232_TO_FBB
            return True
        name = {ord("B"): "point", ord("@"): "stream", ord("Y"): "position_angles", ord("/"): "fbb_reset",
                ord("G"): "sleep", ord("F"): "run"}.get(code, f"unsupported_0x{code:02x}")
        self._count(name)
        if name == "point":
            state.streaming = False
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
            self._write(self._parameter(param).to_bytes(length, "little"))
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
                fob.PARAM_GROUP_MODE: state.group_mode, fob.PARAM_AUTOCONFIG: self.config.sensors}[param]

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
        line_time = self.config.sensors * fob.RECORD_BYTES * fob.BITS_PER_BYTE_ON_WIRE / self.config.baud
        while self._next_due <= now and self._master >= 0:
            due = self._next_due
            k = self._cycle
            self._cycle += 1
            self._next_due += period
            if not self._state.streaming:
                continue
            if due < self._stall_until:
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
        sensors = range(1, self.config.sensors + 1) if group else (self._state.addressed,)
        records = [fob.encode_record(words[s - 1], s if group else None) for s in sensors]
        wire, damaged = self._apply_line_faults(records)
        if self._write(wire):
            tally = self._tally
            (tally.point_counters if point else tally.stream_counters).append(k)
            if not point:
                tally.stream_t_model_s.append(t_model)
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
        cfg, wire, damaged = self.config, bytearray(), []
        for index, record in enumerate(records):
            hit = False
            for byte in record:
                roll = self._rng.random() if cfg.corrupt or cfg.drop else 1.0
                if roll < cfg.drop:
                    self._tally.bytes_dropped += 1
                    hit = True
                    continue
                if roll < cfg.drop + cfg.corrupt:
                    byte = int(self._rng.integers(0, 128)) | (0 if byte & 0x80 else 0x80)
                    self._tally.bytes_corrupted += 1
                    hit = True
                wire.append(byte)
            if hit:
                damaged.append(index)
        return bytes(wire), damaged

    def _write(self, data: bytes) -> bool:
        """Write to the pty; bytes the host's buffer cannot take are lost (counted). True if all went."""
        try:
            written = os.write(self._master, data)
        except BlockingIOError:
            written = 0
        except OSError:
            return False
        self._tally.bytes_sent += written
        self._tally.bytes_lost_host_buffer += len(data) - written
        return written == len(data)

    # -- plugging -----------------------------------------------------------------------------------
    def _plug_in(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.pty_path = os.ttyname(slave)
        if self.config.link:
            temporary = f"{self.config.link}.{os.getpid()}.tmp"
            os.symlink(self.pty_path, temporary)
            os.replace(temporary, self.config.link)
        log.info("trakSTAR emulator serving on %s", self.path)

    def _unplug_fds(self) -> None:
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1
        self._commands.clear()
        self._state = _State()
        if self.config.link and os.path.islink(self.config.link):
            os.unlink(self.config.link)

    def _maybe_replug(self, now: float) -> None:
        if now < self._unplug_until or self._stop.is_set():
            return
        with self._lock:
            self._plug_in()
            self._restart_cycles(now)
            self._tally.unplugs[-1].update(replugged_ns=time.time_ns(), path=self.pty_path)

    def _scheduled_faults(self, now: float) -> None:
        elapsed = now - self._t0
        cfg = self.config
        if 0 <= cfg.stall_at <= elapsed and "stall" not in self._scheduled_faults_done:
            self._scheduled_faults_done.add("stall")
            self.stall(cfg.stall_for)
        if 0 <= cfg.unplug_at <= elapsed and "unplug" not in self._scheduled_faults_done:
            self._scheduled_faults_done.add("unplug")
            self.unplug(cfg.unplug_for)


def serve_for(emulator: TrakstarEmulator, duration_s: float | None, should_stop) -> None:
    """Run ``emulator`` in a thread until ``duration_s`` has passed or ``should_stop()`` is true."""
    if not emulator.running:
        emulator.start()
    deadline = None if duration_s is None else time.monotonic() + duration_s
    while not should_stop() and (deadline is None or time.monotonic() < deadline):
        if not emulator.running:
            raise DeviceError("the trakSTAR emulator stopped unexpectedly (see the log)")
        time.sleep(0.05)
