"""An FPS pedal board on a pseudo-terminal, speaking exactly the firmware's MIDAS-FPS v1 protocol.

The emulator owns a pty (``os.openpty``); the driver opens its slave path like any serial port. It
answers ``ID``/``RATE``/``START``/``STOP`` as firmware/fps/main.c does, and while started writes one
sample line at each tick of the sample clock (host monotonic time, catching up if it fell behind),
whole lines only (with ``send_log``, each sample is logged as ``boot,seq`` when the write of its
line's last byte returned: :mod:`~midas_cli.devices.send_log`). Values come from the simulated
surgeon's feet (:meth:`SurgeonMotion.pedal_adc`, ``pedals="model"``) or a resting foot
(``pedals="idle"``); :meth:`force` presses or releases a channel.

Faults are the :class:`~midas_cli.devices.pty_emulator.Faults` of every pty emulator: per-byte
corruption and drop on everything the board sends; a stall (the board neither reads nor writes,
samples due meanwhile are skipped: their sequence numbers are never sent); an unplug window. The pty,
its ``link`` and the serving thread are :class:`~midas_cli.devices.pty_emulator.PtyEmulator`'s. A
replug is a reboot, as on a real board: the counter restarts at 0 and the banner is sent.

:meth:`summary` tells exactly what was sent, sample by sample, so tests can prove zero loss.
"""

from __future__ import annotations

import select
import time
from array import array
from collections import deque
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.clock import HostClock
from midas_cli.devices.fps.protocol import (
    CommandBuffer, Command, encode_banner, encode_error, encode_ok, encode_sample, rate_fits,
)
from midas_cli.devices.pty_emulator import Faults, PtyEmulator
from midas_cli.errors import ConfigError
from midas_cli.synthetic.surgeon import MotionConfig, SurgeonMotion

FIRMWARE = "1.0.0"
MCU = "emulator"
TX_BUFFER_BYTES = 4096
IDLE_WAIT_S = 0.02
REST_MODEL_T_S = 0.5  # the model has no presses in its first second: rest levels are taken here
CLOCK_DRIFT = 20e-6  # the board's crystal runs 20 ppm fast


@dataclass(frozen=True)
class FpsEmulatorConfig:
    """Board settings and faults (fault times are seconds since :meth:`FpsEmulator.start`)."""

    channels: int = 9
    rate_hz: int = 250
    baud: int = 500_000
    seed: int = 0
    pedals: str = "model"
    press_counts: int = 700
    faults: Faults = Faults()
    link: Path | None = None
    keep_samples: bool = True
    send_log: str | None = None  # log each sample's send time here (devices/send_log.py)

    def __post_init__(self) -> None:
        if not 1 <= self.channels <= 9:
            raise ConfigError(f"emulator channels must be 1..9, got {self.channels}")
        if self.pedals not in ("model", "idle"):
            raise ConfigError(f"emulator pedals must be 'model' or 'idle', got {self.pedals!r}")
        if not rate_fits(self.rate_hz, self.channels, self.baud):
            raise ConfigError(f"emulator rate {self.rate_hz} Hz does not fit {self.channels} channels at {self.baud} baud")
        if not 0 <= self.press_counts <= 1023:
            raise ConfigError(f"emulator press_counts must be 0..1023, got {self.press_counts}")


@dataclass
class _Boot:
    """State of the board since its last (re)boot."""

    index: int
    mono: float
    rate_hz: int
    seq: int = 0
    running: bool = False
    tick_origin: float = 0.0
    ticks: int = 0
    skipped: int = 0


class _SampleLog:
    """Every sample sent, kept in flat typed arrays: a long run (a 30-minute soak sends 1.5 million)
    would otherwise hold millions of GC-tracked dicts and lists, and the emulator would pause for whole
    collections, long enough for a host to see the board stall."""

    def __init__(self) -> None:
        self.boot, self.seq, self.t_us = array("l"), array("q"), array("q")
        self.adc, self.intact, self.width = array("h"), array("b"), 0

    def append(self, boot: int, seq: int, t_us: int, adc: list[int], intact: bool) -> None:
        self.width = self.width or len(adc)
        self.boot.append(boot)
        self.seq.append(seq)
        self.t_us.append(t_us)
        self.adc.extend(adc)
        self.intact.append(intact)

    def as_dicts(self) -> list[dict[str, Any]]:
        w = self.width
        return [{"boot": b, "seq": q, "t_us": t, "adc": self.adc[i * w : (i + 1) * w].tolist(), "intact": bool(k)}
                for i, (b, q, t, k) in enumerate(zip(self.boot, self.seq, self.t_us, self.intact))]


@dataclass
class _Tally:
    sent: int = 0
    intact: int = 0
    skipped_stall: int = 0
    skipped_tx_full: int = 0
    commands: dict[str, int] = field(default_factory=dict)
    samples: _SampleLog = field(default_factory=_SampleLog)
    boots: list[dict[str, Any]] = field(default_factory=list)


class FpsEmulator(PtyEmulator):
    """Run with :meth:`start` (a background thread) and :meth:`stop`; ``path`` is what the driver opens."""

    label = "FPS"
    send_log_identity = ("boot", "seq")

    def __init__(self, config: FpsEmulatorConfig = FpsEmulatorConfig()) -> None:
        super().__init__(config.faults, config.link, config.seed, config.send_log)
        self.config = config
        self.clock = HostClock.anchored_now()
        self.motion = SurgeonMotion(MotionConfig(seed=config.seed))
        self._rest = self.motion.pedal_adc(np.array([REST_MODEL_T_S]))[0, : config.channels].astype(int)
        self._forced: list[bool | None] = [None] * config.channels
        self._tally = _Tally()
        self._out = bytearray()
        self._bytes_out = 0  # written since the (re)plug
        self._unlogged: deque[tuple[int, tuple[int, int], float]] = deque()  # (end offset, boot/seq, due)
        self._boundary_ok = True
        self._commands = CommandBuffer()
        self._boot: _Boot | None = None

    # ---- public control ------------------------------------------------------------------------------

    def force(self, channel: int, pressed: bool | None) -> None:
        """Hold channel (1-based) pressed (True), released (False), or back to its normal source (None)."""
        if not 1 <= channel <= self.config.channels:
            raise ConfigError(f"channel must be 1..{self.config.channels}, got {channel}")
        self._forced[channel - 1] = pressed

    def control(self, line: str) -> None:
        """Text control (``midas emulate fps`` reads these from stdin): ``press N``, ``release N``,
        ``auto N``, ``unplug``, ``replug``."""
        words = line.split()
        actions = {"press": True, "release": False, "auto": None}
        if len(words) == 2 and words[0] in actions and words[1].isdigit():
            self.force(int(words[1]), actions[words[0]])
        elif words in (["unplug"], ["replug"]):
            if words[0] == "unplug" and not self.port.link:  # the host's path would vanish for good
                raise ConfigError("unplug needs --link: without it the host cannot find the board again")
            self.set_unplugged(words[0] == "unplug")
        else:
            raise ConfigError(f"unknown emulator control {line.strip()!r} (press N, release N, auto N, unplug, replug)")

    def _summary(self) -> dict[str, Any]:
        """Counts, boots, and per sample ``boot, seq, t_us, adc, intact`` (intact: no fault touched it or
        the LF before it, so a correct host must have decoded it)."""
        t = self._tally
        return {"config": {k: v for k, v in asdict(self.config).items() if k != "link"},
                "channels": self.config.channels, "sent": t.sent, "intact": t.intact,
                "skipped": {"stall": t.skipped_stall, "tx_full": t.skipped_tx_full},
                "commands": dict(t.commands), "boots": list(t.boots), "samples": t.samples.as_dicts()}

    # ---- plugging ------------------------------------------------------------------------------------

    def _on_plug(self, now: float) -> None:
        self._out.clear()
        self._bytes_out = 0
        self._unlogged.clear()  # lines queued before the unplug never went out
        self._boundary_ok = True
        self._commands = CommandBuffer()
        index = len(self._tally.boots)
        self._boot = _Boot(index, now, self.config.rate_hz)
        with self._lock:
            self._tally.boots.append({"boot": index, "at_s": round(now - self._t0, 6), "t_host_ns": self.clock.now_ns(),
                                      "path": self.port.pty_path})
        self._send(self._banner())

    def _while_unplugged(self, now: float) -> None:
        self._skip_due_samples()

    # ---- serving -------------------------------------------------------------------------------------

    def _step(self, now: float) -> None:
        if self._stalled(now):
            self._skip_due_samples()
            time.sleep(min(IDLE_WAIT_S, self._wait_s()))
            return
        writable = [self.port.master] if self._out else []
        readable, can_write, _ = select.select([self.port.master], writable, [], self._wait_s())
        if readable:
            self._read_commands()
        if can_write or self._out:
            self._flush()
        self._send_due_samples()

    def _wait_s(self) -> float:
        boot = self._boot
        if boot is None or not boot.running:
            return IDLE_WAIT_S
        return max(0.0, min(IDLE_WAIT_S, self._due(boot.ticks) - time.monotonic()))

    def _due(self, tick: int) -> float:
        return self._boot.tick_origin + tick / self._boot.rate_hz

    def _read_commands(self) -> None:
        for command in self._commands.feed(self._read(1024)):
            self._execute(command)

    def _execute(self, command: Command) -> None:
        boot = self._boot
        with self._lock:
            self._tally.commands[command.kind] = self._tally.commands.get(command.kind, 0) + 1
        if command.kind == "ID":
            self._send(self._banner())
        elif command.kind == "ERR":
            self._send(encode_error(str(command.arg)))
        elif command.kind == "RATE" and not rate_fits(int(command.arg), self.config.channels, self.config.baud):
            self._send(encode_error("RANGE"))
        elif command.kind == "RATE":
            boot.rate_hz = int(command.arg)
            self._restart_ticks()
            self._send(encode_ok("RATE", boot.rate_hz))
        elif command.kind in ("START", "STOP"):
            boot.running = command.kind == "START"
            self._send(encode_ok(command.kind))
            self._restart_ticks()

    def _restart_ticks(self) -> None:
        self._boot.tick_origin = time.monotonic() + 1.0 / self._boot.rate_hz
        self._boot.ticks = 0

    def _banner(self) -> bytes:
        b = self._boot
        return encode_banner(FIRMWARE, MCU, self.config.channels, b.rate_hz, self.config.baud, b.running, b.skipped)

    # ---- samples -------------------------------------------------------------------------------------

    def _due_count(self) -> int:
        boot = self._boot
        if boot is None or not boot.running:
            return 0
        now = time.monotonic()
        return max(0, int(np.floor((now - boot.tick_origin) * boot.rate_hz)) + 1 - boot.ticks)

    def _skip_due_samples(self) -> None:
        count = self._due_count()
        if count:
            self._boot.ticks += count
            self._boot.seq += count
            self._boot.skipped += count
            with self._lock:
                self._tally.skipped_stall += count

    def _send_due_samples(self) -> None:
        count = self._due_count()
        if not count:
            return
        boot = self._boot
        due = boot.tick_origin + (boot.ticks + np.arange(count)) / boot.rate_hz
        adc = self._values(due - self._t0)
        for i in range(count):
            t_us = int(round((due[i] - boot.mono) * 1e6 * (1 + CLOCK_DRIFT))) % (1 << 32)
            self._emit_sample(boot.seq, t_us, adc[i], float(due[i]))
            boot.seq += 1
        boot.ticks += count

    def _values(self, t: np.ndarray) -> np.ndarray:
        """ADC counts (N, channels) at emulator times t (s since start)."""
        n = self.config.channels
        if self.config.pedals == "model":
            adc = self.motion.pedal_adc(t)[:, :n].astype(int)
        else:
            adc = np.tile(self._rest, (len(t), 1)) + np.rint(self._rng.normal(0.0, 1.5, (len(t), n))).astype(int)
        for c, forced in enumerate(self._forced):
            if forced is not None:
                level = self.config.press_counts if forced else self._rest[c]
                adc[:, c] = level + np.rint(self._rng.normal(0.0, 1.5, len(t))).astype(int)
        return np.clip(adc, 0, 1023)

    def _emit_sample(self, seq: int, t_us: int, adc: np.ndarray, due: float) -> None:
        if len(self._out) > TX_BUFFER_BYTES:
            self._boot.skipped += 1
            with self._lock:
                self._tally.skipped_tx_full += 1
            return
        values = [int(a) for a in adc]
        intact = self._send(encode_sample(seq % (1 << 32), t_us, values), ((self._boot.index, seq), due))
        with self._lock:
            self._tally.sent += 1
            self._tally.intact += intact
            if self.config.keep_samples:
                self._tally.samples.append(self._boot.index, seq, t_us, values, intact)

    def _send(self, line: bytes, sample: tuple[tuple[int, int], float] | None = None) -> bool:
        """Queue a line through the fault injector; True if a correct host must decode it: it goes out
        unaltered and the line before it still ends in an LF (else the two merge into one bad line).
        ``sample``: the line's (boot, seq) and due time, for the send log."""
        with self._lock:
            data = self._damage(line)
        decodable = data == line and self._boundary_ok
        self._boundary_ok = data.endswith(b"\n")
        self._out += data
        if sample is not None and self.send_log is not None:
            self._unlogged.append((self._bytes_out + len(self._out), *sample))
        self._flush()
        return decodable

    def _flush(self) -> None:
        if not self.port.plugged or not self._out:
            return
        written = self._write(bytes(self._out))
        if written > 0:
            del self._out[:written]
            self._bytes_out += written
            self._log_sent()

    def _log_sent(self) -> None:
        """Log the samples whose last byte the write that just returned carried."""
        if self.send_log is None:
            return
        while self._unlogged and self._unlogged[0][0] <= self._bytes_out:
            _, identity, due = self._unlogged.popleft()
            self.send_log.record(identity, due, self.last_write_ns)
