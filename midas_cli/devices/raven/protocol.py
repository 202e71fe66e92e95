"""The Raven-II teleoperation packet (``u_struct`` in the Raven 2 Control software's
``include/itp_teleoperation.h``, packed, little-endian x86): 124 bytes sent by the surgeon console
(master) to the robot (slave) over UDP, port 36000 by default.

Layout ``<IIIiiiiiiddddddddiiiiii``: sequence, pactyp, version (uint32); delx[2], dely[2], delz[2]
(int32 position increments per arm, micrometres in the ITP frame); Qx[2], Qy[2], Qz[2], Qw[2] (float64
orientation quaternion per arm); buttonstate[2], grasp[2] (int32; grasp +32767 = 100 % closing torque,
-32768 = 100 % opening); surgeon_mode (1 engaged = pedal down, 0 disengaged); checksum. Arrays are
stored field by field (delx[0], delx[1], dely[0], ...), index 0 and 1 being the two arms.

The checksum is the Raven's ``UDPChecksum``: surgeon_mode + delx/dely/delz of both arms + both
buttonstates + sequence, in 32-bit signed arithmetic (the robot computes but does not enforce it).
Sequence 0 means "reflect this packet" on the robot and is not teleoperation data.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from midas_cli.errors import DeviceError

U_STRUCT = struct.Struct("<IIIiiiiiiddddddddiiiiii")
PACKET_SIZE = U_STRUCT.size  # 124
ARMS = (0, 1)
SURGEON_ENGAGED = 1
SURGEON_DISENGAGED = 0


@dataclass(frozen=True)
class RavenPacket:
    """One decoded ``u_struct``. Per-arm tuples are (arm 0, arm 1)."""

    sequence: int
    pactyp: int
    version: int
    delx: tuple[int, int]
    dely: tuple[int, int]
    delz: tuple[int, int]
    qx: tuple[float, float]
    qy: tuple[float, float]
    qz: tuple[float, float]
    qw: tuple[float, float]
    buttonstate: tuple[int, int]
    grasp: tuple[int, int]
    surgeon_mode: int
    checksum: int

    @property
    def checksum_ok(self) -> bool:
        return self.checksum == raven_checksum(self)

    def row_values(self) -> tuple:
        """Values in the order of the stream columns after seq/t_host_ns (see ``device.COLUMNS``)."""
        per_arm = []
        for arm in ARMS:
            per_arm += [self.delx[arm], self.dely[arm], self.delz[arm], self.qx[arm], self.qy[arm], self.qz[arm],
                        self.qw[arm], self.buttonstate[arm], self.grasp[arm]]
        return (self.sequence, self.pactyp, self.version, *per_arm, self.surgeon_mode, self.checksum,
                int(self.checksum_ok))


def _wrap_int32(value: int) -> int:
    return (value + 2**31) % 2**32 - 2**31


def raven_checksum(p: RavenPacket) -> int:
    """The Raven's UDPChecksum of a packet (32-bit signed wrap-around)."""
    total = p.surgeon_mode + sum(p.delx) + sum(p.dely) + sum(p.delz) + sum(p.buttonstate) + _wrap_int32(p.sequence)
    return _wrap_int32(total)


def decode_packet(data: bytes) -> RavenPacket:
    """Decode exactly one 124-byte packet; DeviceError for any other size."""
    if len(data) != PACKET_SIZE:
        raise DeviceError(f"Raven packet of {len(data)} bytes, expected {PACKET_SIZE} (u_struct)")
    v = U_STRUCT.unpack(data)
    return RavenPacket(v[0], v[1], v[2], (v[3], v[4]), (v[5], v[6]), (v[7], v[8]), (v[9], v[10]), (v[11], v[12]),
                       (v[13], v[14]), (v[15], v[16]), (v[17], v[18]), (v[19], v[20]), v[21], v[22])


def encode_packet(p: RavenPacket) -> bytes:
    """The 124 bytes of a packet (its ``checksum`` field as given)."""
    return U_STRUCT.pack(p.sequence, p.pactyp, p.version, *p.delx, *p.dely, *p.delz, *p.qx, *p.qy, *p.qz, *p.qw,
                         *p.buttonstate, *p.grasp, p.surgeon_mode, p.checksum)


@dataclass
class SequenceTracker:
    """Counts what the packet sequence numbers say about the link (the robot's own categories):
    gaps (packets skipped), duplicates, out-of-order packets and resets (a jump back by more than 1000,
    e.g. the console restarted)."""

    last: int | None = None
    gaps: int = 0
    missing: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    resets: int = 0

    def update(self, sequence: int) -> None:
        last = self.last
        if last is None or sequence == last + 1:
            self.last = sequence
        elif sequence > last + 1:
            self.gaps += 1
            self.missing += sequence - last - 1
            self.last = sequence
        elif sequence == last:
            self.duplicates += 1
        elif last > 1000 and sequence < last - 1000:
            self.resets += 1
            self.last = sequence
        else:
            self.out_of_order += 1

    def summary(self) -> dict[str, int]:
        return {"sequence_gaps": self.gaps, "sequence_missing": self.missing, "duplicates": self.duplicates,
                "out_of_order": self.out_of_order, "sequence_resets": self.resets}
