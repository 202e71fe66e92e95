"""Pure bytes codec of the Flock-of-Birds-compatible RS-232 protocol spoken by the trakSTAR (DESIGN.md §6).

No I/O here: commands are built as ``bytes``, replies and data records are parsed from ``bytes``.

Wire format of a POSITION/ANGLES record ('Y'), group mode: 12 data bytes (6 words, LS byte first)
followed by one address byte (the sensor's bus address 1..N), 13 bytes in all. Every byte carries 7
data bits; bit 7 is the *phasing bit*, set on the first byte of a record and clear on every other
byte (the address byte included). A word is ``signed((msb & 0x7f) << 9 | (lsb & 0x7f) << 2)``;
positions are ``word * range / 32768`` inches (range 36 or 72), angles ``word * 180 / 32768`` degrees
in the order x, y, z, azimuth, elevation, roll.

Framing is all the protocol offers (there is no checksum): :class:`RecordDecoder` accepts a record
only when its phasing bits are exactly where they belong, it is exactly 13 bytes long, its address is
in 1..sensors and its elevation lies within ±90°. "Exactly 13 bytes" is proven by what follows it:
either the next byte starts a record (the lookahead), or, for the last record of a burst, the line
stays idle after it (:meth:`RecordDecoder.accept_pending`, called by the driver once no byte came for
16 byte times: an extra byte inside or after a record arrives back to back with it at wire speed, so
silence confirms the boundary without waiting a whole cycle for the next record). Noise that leaves
the phasing bits intact and the values plausible cannot be detected by any decoder of this protocol.

Examine/change value: ``'O' param`` answers with the parameter's bytes (words LS byte first, 8 data
bits, no phasing); ``'P' param data`` changes it. Parameters used here: 1 software revision,
3 position scaling (0 = 36 in, 1 = 72 in), 7 measurement rate (Hz x 256), 25 serial number,
35 group mode (1 byte), 50 FBB auto-configuration (1 byte: number of sensors).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

POINT = b"B"
STREAM = b"@"
POSITION_ANGLES = b"Y"
FBB_RESET = b"/"
EXAMINE = b"O"
CHANGE = b"P"
RS232_TO_FBB = 0xF0  # + address (1..14): the next command goes to that sensor

PARAM_REVISION = 1
PARAM_POSITION_SCALING = 3
PARAM_MEASUREMENT_RATE = 7
PARAM_SERIAL_NUMBER = 25
PARAM_GROUP_MODE = 35
PARAM_AUTOCONFIG = 50
WORD_PARAMS = (PARAM_REVISION, PARAM_POSITION_SCALING, PARAM_MEASUREMENT_RATE, PARAM_SERIAL_NUMBER)
BYTE_PARAMS = (PARAM_GROUP_MODE, PARAM_AUTOCONFIG)

RANGES_IN = {36: 0, 72: 1}  # position range (inches) -> position scaling code
MM_PER_INCH = 25.4
WORDS = 6
DATA_BYTES = 2 * WORDS
RECORD_BYTES = DATA_BYTES + 1  # + address byte (group mode)
BITS_PER_BYTE_ON_WIRE = 10  # 8N1: start + 8 data + stop
MAX_SENSORS = 14
MAX_RATE_HZ = 65535 / 256


# ---- commands --------------------------------------------------------------------------------------

def examine(param: int) -> bytes:
    """EXAMINE VALUE command for ``param``."""
    return EXAMINE + bytes([param])


def change_word(param: int, value: int) -> bytes:
    """CHANGE VALUE command with a 16-bit word (LS byte first)."""
    return CHANGE + bytes([param]) + int(value).to_bytes(2, "little", signed=False)


def change_byte(param: int, value: int) -> bytes:
    """CHANGE VALUE command with a single byte."""
    return CHANGE + bytes([param, value])


def to_sensor(address: int) -> bytes:
    """RS232-TO-FBB prefix: the next command is for the sensor at ``address`` (1..14)."""
    if not 1 <= address <= MAX_SENSORS:
        raise ValueError(f"sensor address must be 1..{MAX_SENSORS}, got {address}")
    return bytes([RS232_TO_FBB + address])


def rate_word(rate_hz: float) -> int:
    """Measurement rate in Hz -> the parameter word (Hz x 256)."""
    word = int(round(rate_hz * 256))
    if not 0 < word <= 0xFFFF:
        raise ValueError(f"measurement rate {rate_hz} Hz does not fit the protocol (0 < rate <= {MAX_RATE_HZ:.2f})")
    return word


def reply_length(param: int) -> int:
    """Bytes in the EXAMINE reply of ``param``."""
    if param in WORD_PARAMS:
        return 2
    if param in BYTE_PARAMS:
        return 1
    raise ValueError(f"EXAMINE of parameter {param} is not supported by this codec")


def parse_reply(param: int, reply: bytes) -> int:
    """The value of an EXAMINE reply (unsigned word LS byte first, or one byte)."""
    if len(reply) != reply_length(param):
        raise ValueError(f"EXAMINE {param}: expected {reply_length(param)} bytes, got {len(reply)}")
    return int.from_bytes(reply, "little", signed=False)


def line_capacity_hz(baud: int, sensors: int) -> float:
    """Group records per second (each sensor once) an 8N1 line at ``baud`` can carry."""
    return baud / BITS_PER_BYTE_ON_WIRE / (sensors * RECORD_BYTES)


# ---- records ---------------------------------------------------------------------------------------

def scales(range_in: int) -> np.ndarray:
    """Per-word factor (6,) from the signed 16-bit word to mm (x, y, z) and degrees (a, e, r)."""
    position = range_in * MM_PER_INCH / 32768.0
    return np.array([position] * 3 + [180.0 / 32768.0] * 3)


def words_from_values(values: np.ndarray, range_in: int) -> np.ndarray:
    """Quantise values (..., 6) mm/deg to the words (..., 6) int16 a device sends (14 significant bits).

    Angles wrap into [-180, 180); positions outside ±range are refused (the device cannot report them).
    """
    values = np.asarray(values, dtype=np.float64).copy()
    values[..., 3:] = (values[..., 3:] + 180.0) % 360.0 - 180.0
    counts = np.round(values / scales(range_in) / 4.0).astype(np.int64) * 4
    if (np.abs(counts[..., :3]) > 32764).any():
        raise ValueError(f"position outside the ±{range_in} in range of the transmitter")
    return np.clip(counts, -32768, 32764).astype(np.int16)


def values_from_words(words: np.ndarray, range_in: int) -> np.ndarray:
    """Words (..., 6) int -> values (..., 6): x, y, z mm, azimuth, elevation, roll degrees."""
    return np.asarray(words, dtype=np.float64) * scales(range_in)


def encode_record(words: np.ndarray, address: int | None) -> bytes:
    """One POSITION/ANGLES record: 12 data bytes with the phasing bit on the first, then (group mode
    only, ``address`` not None) the sensor's address byte."""
    out = bytearray()
    for word in np.asarray(words, dtype=np.int64).tolist():
        unsigned = word & 0xFFFF
        out += bytes([(unsigned >> 2) & 0x7F, (unsigned >> 9) & 0x7F])
    out[0] |= 0x80
    if address is not None:
        out.append(address & 0x7F)
    return bytes(out)


def decode_words(data: bytes) -> list[int]:
    """The 6 signed words of a record's 12 data bytes."""
    words = []
    for i in range(0, DATA_BYTES, 2):
        raw = ((data[i + 1] & 0x7F) << 9) | ((data[i] & 0x7F) << 2)
        words.append(raw - 0x10000 if raw & 0x8000 else raw)
    return words


@dataclass(frozen=True)
class Record:
    """One framed record: bus address (1..N), values (x, y, z mm, a, e, r deg), host time of the read,
    and how many bytes the decoder discarded between the previous accepted record and this one."""

    address: int
    values: tuple[float, ...]
    t_host_ns: int
    discarded_before: int = 0


@dataclass
class DecoderCounts:
    """What the decoder saw: accepted records, rejected candidates and every byte it threw away."""

    records: int = 0
    idle_accepted: int = 0  # of ``records``: accepted on line silence instead of the next record's first byte
    rejected: int = 0
    discarded_bytes: int = 0
    reasons: dict[str, int] = field(default_factory=dict)


class RecordDecoder:
    """Incremental decoder of group-mode POSITION/ANGLES records, fed arbitrary byte chunks.

    After a corrupted or lost byte it throws bytes away up to the next byte with the phasing bit
    (counting them) and never emits a record that failed framing. Each record says how many bytes
    vanished since the previous one (``Record.discarded_before``), to estimate lost records.

    :meth:`feed` accepts a record when the first byte of the next one has arrived; a complete record at
    the end of what was fed (:attr:`pending`) waits for that byte, or for :meth:`accept_pending` once the
    caller has seen the line stay idle after it.

    Record times: the host time of the read that completed the record, minus the line time
    (``byte_ns`` per byte) of the bytes that followed it in the same read, since they arrived after it;
    so the records of one read get distinct, increasing times.
    """

    def __init__(self, sensors: int, range_in: int, byte_ns: int = 0) -> None:
        if not 1 <= sensors <= MAX_SENSORS:
            raise ValueError(f"sensors must be 1..{MAX_SENSORS}, got {sensors}")
        self.sensors = sensors
        self.range_in = range_in
        self.byte_ns = byte_ns
        self._scales = scales(range_in).tolist()
        self._buffer = bytearray()
        self.counts = DecoderCounts()
        self._discarded_since_record = 0
        self._complete_ns: int | None = None  # host time the candidate at the buffer start became complete

    def feed(self, chunk: bytes, t_host_ns: int) -> list[Record]:
        """Decode ``chunk`` (read at host time ``t_host_ns``); returns the records it completed."""
        self._buffer += chunk
        records: list[Record] = []
        while True:
            self._skip_to_phasing_byte()
            if len(self._buffer) <= RECORD_BYTES:
                if len(self._buffer) == RECORD_BYTES and self._complete_ns is None:
                    self._complete_ns = t_host_ns
                return records
            record = self._take_record(t_host_ns)
            if record is not None:
                records.append(record)

    @property
    def pending(self) -> bool:
        """True when the buffer holds exactly one complete candidate record (13 bytes from a phasing byte)
        that only waits for its lookahead byte."""
        return len(self._buffer) == RECORD_BYTES and bool(self._buffer[0] & 0x80)

    def accept_pending(self) -> list[Record]:
        """Frame the :attr:`pending` record without its lookahead byte; returns it, or [] if none is pending
        or it fails framing (bytes discarded and counted as in :meth:`feed`).

        Call only when no byte has arrived since the one that completed it for longer than the host can
        hold back a byte of a running transmission (see the driver's idle window): an inserted or extra
        byte would then already be here, and is still rejected by :meth:`feed` when it is."""
        if not self.pending:
            return []
        record = self._take_record(self._complete_ns, lookahead=False)
        self._skip_to_phasing_byte()
        if record is None:
            return []
        self.counts.idle_accepted += 1
        return [record]

    def _skip_to_phasing_byte(self) -> None:
        start = next((i for i, b in enumerate(self._buffer) if b & 0x80), len(self._buffer))
        if start:
            self._discard(start, "no phasing bit")

    def _take_record(self, t_host_ns: int, lookahead: bool = True) -> Record | None:
        """Frame the 13 bytes at the buffer start (which has the phasing bit), with the byte after them
        when ``lookahead``; None if they fail."""
        candidate = bytes(self._buffer[:RECORD_BYTES])
        early = next((i for i in range(1, RECORD_BYTES) if candidate[i] & 0x80), None)
        if early is not None:
            self._discard(early, "record too short")
            return None
        if lookahead and not self._buffer[RECORD_BYTES] & 0x80:
            self._discard(1, "record too long")
            return None
        address = candidate[DATA_BYTES]
        if not 1 <= address <= self.sensors:
            self._discard(1, "address out of range")
            return None
        values = tuple(w * s for w, s in zip(decode_words(candidate), self._scales))
        if abs(values[4]) > 90.0:
            self._discard(1, "elevation out of range")
            return None
        del self._buffer[:RECORD_BYTES]
        self.counts.records += 1
        discarded, self._discarded_since_record = self._discarded_since_record, 0
        completed_ns = self._complete_ns
        if completed_ns is None:
            completed_ns = t_host_ns - len(self._buffer) * self.byte_ns
        self._complete_ns = None
        return Record(address, values, completed_ns, discarded)

    def _discard(self, count: int, reason: str) -> None:
        del self._buffer[:count]
        self._complete_ns = None
        self.counts.discarded_bytes += count
        self._discarded_since_record += count
        if reason != "no phasing bit":
            self.counts.rejected += 1
        self.counts.reasons[reason] = self.counts.reasons.get(reason, 0) + 1


@dataclass(frozen=True)
class Group:
    """One measurement cycle: ``index`` counts cycles since the stream started (gaps = lost cycles);
    ``values[k]`` is sensor k+1's values or None when its record failed framing or was lost."""

    index: int
    t_host_ns: int
    values: tuple[tuple[float, ...] | None, ...]


class GroupAssembler:
    """Groups decoded records into measurement cycles (sensor 1..N, one record each, in order).

    Each accepted record is placed in the stream of record slots (slot = cycle * N + address - 1) at
    the slot with its address nearest to where the bytes discarded since the previous record say it
    should be (one slot per 13 discarded bytes), so lost records, even whole lost cycles, are counted
    and never mix two cycles into one row. ``missing`` counts sensor records that never arrived.
    """

    def __init__(self, sensors: int) -> None:
        self.sensors = sensors
        self.missing = 0
        self._last_slot: int | None = None
        self._index: int | None = None
        self._values: list[tuple[float, ...] | None] = []
        self._t_host_ns = 0

    def add(self, records: list[Record]) -> list[Group]:
        """Place ``records``; return the cycles completed by them (in order)."""
        groups: list[Group] = []
        for record in records:
            slot = self._slot_of(record)
            index = slot // self.sensors
            if self._index is not None and index != self._index:
                groups.append(self._finish())
            if self._index != index:
                self._start(index, slot)
            self._values[record.address - 1] = record.values
            self._t_host_ns = record.t_host_ns
            self._last_slot = slot
            if record.address == self.sensors:
                groups.append(self._finish())
        return groups

    def _slot_of(self, record: Record) -> int:
        residue = record.address - 1
        if self._last_slot is None:
            return residue
        target = self._last_slot + 1 + int(round(record.discarded_before / RECORD_BYTES))
        below = target - ((target - residue) % self.sensors)
        above = below + self.sensors
        if below <= self._last_slot or target - below > above - target:
            return above
        return below

    def _start(self, index: int, slot: int) -> None:
        if self._last_slot is not None:
            expected_first = (self._last_slot // self.sensors + 1) * self.sensors
            self.missing += max(0, index * self.sensors - expected_first)
        self._index = index
        self._values = [None] * self.sensors

    def _finish(self) -> Group:
        self.missing += sum(v is None for v in self._values)
        group = Group(self._index, self._t_host_ns, tuple(self._values))
        self._index = None
        return group
