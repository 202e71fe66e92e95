"""A Raven-II surgeon console on loopback: sends ``u_struct`` packets over UDP at a fixed rate.

The content follows the simulated surgeon (:class:`~midas_cli.synthetic.surgeon.SurgeonMotion`): per
arm, the position increment is the motion of the hand's grip point (midpoint of the thumb and middle
fingertip sensors) since the previous packet, in micrometres; the orientation is the thumb sensor's;
the grasp torque grows as the fingers close; ``surgeon_mode`` is disengaged while the clutch pedal is
held. Sequence numbers start at 1 (0 asks the robot to reflect the packet). ``sent`` keeps every packet
(time sent, bytes) so tests can prove zero loss and check every decoded field.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from dataclasses import dataclass

import numpy as np

from midas_cli.devices.raven.protocol import (
    SURGEON_DISENGAGED, SURGEON_ENGAGED, RavenPacket, encode_packet, raven_checksum,
)
from midas_cli.errors import ConfigError
from midas_cli.geometry import quaternions_from_angles
from midas_cli.synthetic.feet import CLUTCH_PEDAL
from midas_cli.synthetic.surgeon import MotionConfig, SurgeonMotion

log = logging.getLogger(__name__)

PACTYP = 1
VERSION = 2
BLOCK = 64
OPEN_APERTURE_MM = 40.0
HAND_SENSORS = ((1, 0), (2, 3))  # per arm (left, right hand): (thumb, middle) sensor indices


@dataclass(frozen=True)
class RavenEmulatorConfig:
    """Where to send, how fast, which surgeon. ``corrupt_every`` > 0 sends a wrong-size datagram after
    every that many packets (for tests of the listener's accounting). ``source`` (``HOST`` or
    ``HOST:PORT``) is the address the packets are sent from; empty: the one the route picks."""

    host: str = "127.0.0.1"
    port: int = 36000
    rate_hz: float = 1000.0
    seed: int = 0
    corrupt_every: int = 0
    source: str = ""

    def __post_init__(self) -> None:
        if not 0 < self.rate_hz <= 10000:
            raise ConfigError(f"Raven emulator rate must be in (0, 10000] Hz, got {self.rate_hz}")


class PacketSource:
    """Packets k = 0, 1, ... of the simulated console (packet k describes time k / rate)."""

    def __init__(self, config: RavenEmulatorConfig) -> None:
        self.config = config
        self.motion = SurgeonMotion(MotionConfig(seed=config.seed))
        self._previous_um: np.ndarray | None = None

    def block(self, first: int, count: int) -> list[RavenPacket]:
        t = np.arange(first, first + count) / self.config.rate_hz
        positions, angles = self.motion.sensor_poses(t)  # (N, 4, 3) mm, (N, 4, 3) deg
        grip_um = np.stack([(positions[:, a] + positions[:, b]) / 2 for a, b in HAND_SENSORS], axis=1) * 1000
        grip_um = np.round(grip_um).astype(np.int64)  # (N, 2 arms, 3)
        start = grip_um[:1] if self._previous_um is None else self._previous_um
        deltas = np.diff(np.concatenate([start, grip_um]), axis=0)  # (N, 2, 3) um since the previous packet
        self._previous_um = grip_um[-1:]
        quats = np.stack([quaternions_from_angles(angles[:, thumb]) for thumb, _ in HAND_SENSORS], axis=1)  # (N, 2, 4)
        closing = np.clip(1 - self.motion.grasper_aperture(t) / OPEN_APERTURE_MM, -1, 1)  # (N, 2)
        grasp = np.round(closing * 32767).astype(int)
        clutch = self.motion.pedal_pressed(t)[:, CLUTCH_PEDAL]
        return [self._packet(first + i, deltas[i], quats[i], grasp[i], bool(clutch[i])) for i in range(count)]

    @staticmethod
    def _packet(k: int, delta: np.ndarray, quat: np.ndarray, grasp: np.ndarray, clutch: bool) -> RavenPacket:
        d = delta.tolist()
        q = quat.tolist()
        packet = RavenPacket(
            sequence=k + 1, pactyp=PACTYP, version=VERSION,
            delx=(d[0][0], d[1][0]), dely=(d[0][1], d[1][1]), delz=(d[0][2], d[1][2]),
            qx=(q[0][0], q[1][0]), qy=(q[0][1], q[1][1]), qz=(q[0][2], q[1][2]), qw=(q[0][3], q[1][3]),
            buttonstate=(0, 0), grasp=(int(grasp[0]), int(grasp[1])),
            surgeon_mode=SURGEON_DISENGAGED if clutch else SURGEON_ENGAGED, checksum=0)
        return RavenPacket(**{**packet.__dict__, "checksum": raven_checksum(packet)})


class RavenEmulator:
    """Sends the console's packets on a background thread, paced to ``rate_hz`` (catching up if late)."""

    def __init__(self, config: RavenEmulatorConfig, keep_sent: bool = True) -> None:
        self.config = config
        self.keep_sent = keep_sent
        self.sent: list[tuple[int, bytes]] = []  # (time.monotonic_ns() when sent, datagram)
        self.count = 0
        self.corrupted = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="raven-emulator", daemon=True)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        if config.source:
            host, _, port = config.source.partition(":")
            try:
                self._sock.bind((host, int(port or 0)))
            except (OSError, ValueError) as exc:
                self._sock.close()
                raise ConfigError(f"Raven emulator cannot send from {config.source!r}: {exc}") from None

    @property
    def address(self) -> tuple[str, int]:
        """The (host, port) the packets come from (the port is known once one was sent, or if bound)."""
        return self._sock.getsockname()

    def start(self) -> "RavenEmulator":
        self._thread.start()
        return self

    def stop(self) -> dict[str, int]:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2)
        self._sock.close()
        return {"packets_sent": self.count, "wrong_size_sent": self.corrupted}

    def __enter__(self) -> "RavenEmulator":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        source = PacketSource(self.config)
        period_ns = int(round(1e9 / self.config.rate_hz))
        start = time.monotonic_ns()
        pending: list[RavenPacket] = []
        while not self._stop.is_set():
            due = start + self.count * period_ns
            wait = due - time.monotonic_ns()
            if wait > 0:
                time.sleep(min(wait / 1e9, 0.005))
                continue
            if not pending:
                pending = source.block(self.count, BLOCK)
            self._send(encode_packet(pending.pop(0)))

    def _send(self, datagram: bytes) -> None:
        target = (self.config.host, self.config.port)
        try:
            self._sock.sendto(datagram, target)
        except OSError as exc:  # nobody listening yet, or the listener is reopening: the packet is lost
            log.debug("raven emulator: packet %d not sent: %s", self.count + 1, exc)
        if self.keep_sent:
            self.sent.append((time.monotonic_ns(), datagram))
        self.count += 1
        every = self.config.corrupt_every
        if every and self.count % every == 0:
            self._sock.sendto(datagram[:-4], target)
            self.corrupted += 1
