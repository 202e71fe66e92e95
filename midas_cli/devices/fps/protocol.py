"""MIDAS-FPS line protocol v1: a pure bytes codec (no I/O), byte-identical to firmware/fps/fps_protocol.c.

Board -> host, every line: ``BODY*CCCC\\n`` where CCCC is the CRC-16/CCITT-FALSE of BODY in uppercase hex.

* sample: ``D`` + seq (8 hex) + device microseconds (8 hex) + one 3-hex ADC count (0..3FF) per channel
* banner: ``#MIDAS-FPS proto=1 fw=1.0.0 mcu=atmega328p ch=8 rate=250 baud=500000 run=0 skipped=0``
* replies: ``OK START``, ``OK STOP``, ``OK RATE 250``, ``ERR UNKNOWN|ARG|CRC|LONG|RANGE``

Host -> board: ``ID``, ``START``, ``STOP``, ``RATE <hz>``, each with an optional ``*CCCC`` suffix and LF.
The full grammar is in firmware/fps/PROTOCOL.md. :class:`LineDecoder` turns a byte stream into messages,
resynchronises at every LF, and counts (never emits) lines that fail framing, length or checksum.
"""

from __future__ import annotations

import binascii
from dataclasses import dataclass, field

PROTO_VERSION = 1
MAX_CHANNELS = 9
ADC_MAX = 1023
MAX_RATE_HZ = 1000
CMD_MAX = 31
MAX_LINE = 96
ADC_US_PER_CHANNEL = 104
BANNER_TAG = "#MIDAS-FPS"
ERROR_NAMES = ("NONE", "UNKNOWN", "ARG", "CRC", "LONG", "RANGE")
COMMANDS = ("ID", "START", "STOP", "RATE")
_HEX = b"0123456789ABCDEF"


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final XOR)."""
    return binascii.crc_hqx(data, 0xFFFF)


def sample_line_length(channels: int) -> int:
    """Bytes of one sample line, LF included: 23 + 3 per channel (50 at 9 channels)."""
    return 23 + 3 * channels


def rate_fits(rate_hz: int, channels: int, baud: int) -> bool:
    """The firmware's rule: 1..1000 Hz, sample lines fit the wire (10 bits per byte), and the ADC scan
    (104 us per channel at 16 MHz) takes at most 80 % of the sample period."""
    if not (1 <= rate_hz <= MAX_RATE_HZ and 1 <= channels <= MAX_CHANNELS):
        return False
    if rate_hz * sample_line_length(channels) * 10 > baud:
        return False
    return rate_hz * channels * ADC_US_PER_CHANNEL <= 800_000


def max_rate_hz(channels: int, baud: int) -> int:
    """The highest rate :func:`rate_fits` accepts (0 if none)."""
    return next((r for r in range(MAX_RATE_HZ, 0, -1) if rate_fits(r, channels, baud)), 0)


def finish_line(body: str) -> bytes:
    """``BODY*CCCC\\n`` for an ASCII body."""
    raw = body.encode("ascii")
    return raw + b"*%04X\n" % crc16(raw)


# ---- board -> host messages ----------------------------------------------------------------------


@dataclass(frozen=True)
class Sample:
    """One sample line: the board's sequence number, its microsecond clock (wraps at 2^32), ADC counts."""

    seq: int
    t_us: int
    adc: tuple[int, ...]


@dataclass(frozen=True)
class Banner:
    """The identify line. ``fields`` keeps every key, known or not (forward compatible)."""

    proto: int
    fw: str
    channels: int
    rate_hz: int
    fields: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class Reply:
    """``OK <what> [value]`` or ``ERR <code>``."""

    ok: bool
    what: str
    value: int | None = None


Message = Sample | Banner | Reply


def encode_sample(seq: int, t_us: int, adc: tuple[int, ...] | list[int]) -> bytes:
    """The sample line, as the firmware formats it. Raises ValueError for out-of-range values."""
    if not 1 <= len(adc) <= MAX_CHANNELS:
        raise ValueError(f"a sample has 1..{MAX_CHANNELS} channels, got {len(adc)}")
    if not (0 <= seq < 1 << 32 and 0 <= t_us < 1 << 32 and all(0 <= a <= ADC_MAX for a in adc)):
        raise ValueError(f"sample out of range: seq={seq} t_us={t_us} adc={list(adc)}")
    return finish_line("D%08X%08X" % (seq, t_us) + "".join("%03X" % a for a in adc))


def encode_banner(fw: str, mcu: str, channels: int, rate_hz: int, baud: int, running: bool, skipped: int) -> bytes:
    """The banner line (sent at boot and in answer to ID)."""
    return finish_line(f"{BANNER_TAG} proto={PROTO_VERSION} fw={fw} mcu={mcu} ch={channels} rate={rate_hz} "
                       f"baud={baud} run={int(running)} skipped={skipped}")


def encode_ok(what: str, rate_hz: int = 0) -> bytes:
    """``OK START``, ``OK STOP`` or ``OK RATE <hz>``."""
    return finish_line(f"OK RATE {rate_hz}" if what == "RATE" else f"OK {what}")


def encode_error(code: str) -> bytes:
    """``ERR <code>`` for a code in :data:`ERROR_NAMES`."""
    if code not in ERROR_NAMES[1:]:
        raise ValueError(f"unknown error code {code!r}")
    return finish_line(f"ERR {code}")


def parse_line(line: bytes, channels: int | None = None) -> Message | None:
    """One line without its LF -> a message, or None if it fails framing, length or checksum.

    ``channels`` (from the banner) fixes the expected sample length; None accepts any of 1..9."""
    star = len(line) - 5
    if star < 1 or line[star:star + 1] != b"*" or not _is_hex(line[star + 1:]):
        return None
    body = line[:star]
    if int(line[star + 1:], 16) != crc16(body):
        return None
    if body[:1] == b"D":
        return _parse_sample(body, channels)
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        return None
    if text.startswith(BANNER_TAG + " "):
        return _parse_banner(text)
    return _parse_reply(text)


def _is_hex(raw: bytes) -> bool:
    return bool(raw) and not raw.translate(None, _HEX)  # deleting the hex digits leaves nothing (in C)


def _parse_sample(body: bytes, channels: int | None) -> Sample | None:
    n, rest = divmod(len(body) - 17, 3)
    if rest or not 1 <= n <= MAX_CHANNELS or (channels is not None and n != channels) or not _is_hex(body[1:]):
        return None
    adc = tuple(int(body[17 + 3 * i: 20 + 3 * i], 16) for i in range(n))
    if max(adc) > ADC_MAX:
        return None
    return Sample(int(body[1:9], 16), int(body[9:17], 16), adc)


def _parse_banner(text: str) -> Banner | None:
    pairs = dict(token.split("=", 1) for token in text.split()[1:] if "=" in token)
    try:
        return Banner(int(pairs["proto"]), pairs["fw"], int(pairs["ch"]), int(pairs["rate"]), pairs)
    except (KeyError, ValueError):
        return None


def _parse_reply(text: str) -> Reply | None:
    words = text.split(" ")
    if words[0] == "OK" and words[1:] in (["START"], ["STOP"]):
        return Reply(True, words[1])
    if words[0] == "OK" and len(words) == 3 and words[1] == "RATE" and words[2].isdigit():
        return Reply(True, "RATE", int(words[2]))
    if words[0] == "ERR" and len(words) == 2 and words[1] in ERROR_NAMES[1:]:
        return Reply(False, words[1])
    return None


@dataclass
class LineDecoder:
    """Bytes -> messages. An invalid first line after (re)connecting is a line torn by the connection, not
    corruption: it counts in ``discarded_bytes`` only. Every later line that fails :func:`parse_line`, or grows past
    :data:`MAX_LINE` bytes without an LF, counts in ``corrupt_lines`` and ``discarded_bytes``."""

    channels: int | None = None
    synced: bool = False
    corrupt_lines: int = 0
    discarded_bytes: int = 0
    _pending: bytearray = field(default_factory=bytearray)

    def feed(self, data: bytes) -> list[Message]:
        """All complete messages in ``data`` (plus what an earlier call left unfinished), in order."""
        self._pending += data
        messages: list[Message] = []
        start = 0
        while (end := self._pending.find(b"\n", start)) >= 0:
            line = bytes(self._pending[start:end])
            start = end + 1
            self._take(line, messages)
        del self._pending[:start]
        if len(self._pending) > MAX_LINE:
            self._reject(len(self._pending))
            self._pending.clear()
        return messages

    def _take(self, line: bytes, messages: list[Message]) -> None:
        message = parse_line(line, self.channels) if len(line) < MAX_LINE else None
        if message is not None:
            messages.append(message)
        elif self.synced:
            self._reject(len(line) + 1)
        else:
            self.discarded_bytes += len(line) + 1
        self.synced = True

    def _reject(self, nbytes: int) -> None:
        self.corrupt_lines += 1
        self.discarded_bytes += nbytes


# ---- host -> board commands ----------------------------------------------------------------------


@dataclass(frozen=True)
class Command:
    """A parsed command: kind in ``NONE ID START STOP RATE ERR``; ``arg`` is the rate or the error code."""

    kind: str
    arg: int | str | None = None


def encode_command(kind: str, rate_hz: int | None = None, checksum: bool = True) -> bytes:
    """``ID``/``START``/``STOP``/``RATE <hz>`` with a ``*CCCC`` suffix (the board also accepts none)."""
    if kind not in COMMANDS or (kind == "RATE") != (rate_hz is not None):
        raise ValueError(f"cannot encode command {kind!r} with rate {rate_hz!r}")
    body = f"RATE {rate_hz}" if kind == "RATE" else kind
    return finish_line(body) if checksum else (body + "\n").encode("ascii")


def parse_command(line: bytes) -> Command:
    """One received command line without its LF, exactly as the firmware's ``fps_parse_command``."""
    if line.endswith(b"\r"):
        line = line[:-1]
    if not line:
        return Command("NONE")
    if len(line) > CMD_MAX:
        return Command("ERR", "LONG")
    body = _checked_body(line)
    if body is None:
        return Command("ERR", "CRC")
    if body in (b"ID", b"START", b"STOP"):
        return Command(body.decode())
    if body[:4] == b"RATE" and (len(body) == 4 or body[4:5] == b" "):
        digits = body[5:]
        if not 1 <= len(digits) <= 5 or not all(48 <= b <= 57 for b in digits):
            return Command("ERR", "ARG")
        return Command("RATE", int(digits))
    return Command("ERR", "UNKNOWN")


def _checked_body(line: bytes) -> bytes | None:
    star = line.rfind(b"*")
    if star < 0:
        return line
    suffix = line[star + 1:]
    if len(suffix) != 4 or not all(b in b"0123456789ABCDEFabcdef" for b in suffix):
        return None
    return line[:star] if int(suffix, 16) == crc16(line[:star]) else None


@dataclass
class CommandBuffer:
    """Bytes -> command lines, as the firmware's ``fps_line_feed``: a line longer than CMD_MAX + 1 bytes
    is answered with ERR LONG."""

    _buf: bytearray = field(default_factory=bytearray)
    _overflow: bool = False

    def feed(self, data: bytes) -> list[Command]:
        commands = []
        for byte in data:
            if byte != 10:
                if len(self._buf) < CMD_MAX + 1:
                    self._buf.append(byte)
                else:
                    self._overflow = True
                continue
            commands.append(Command("ERR", "LONG") if self._overflow else parse_command(bytes(self._buf)))
            self._buf.clear()
            self._overflow = False
        return commands
