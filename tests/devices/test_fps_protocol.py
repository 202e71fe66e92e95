"""The MIDAS-FPS codec: formatting, checksums, torn and corrupted lines, command parsing."""

from __future__ import annotations

import numpy as np
import pytest

from midas_cli.devices.fps import protocol as p


def test_sample_line_layout_and_round_trip() -> None:
    line = p.encode_sample(0x1234, 3_000_000, [0, 512, 1023])
    assert line[:27] == b"D00001234002DC6C00002003FF*" and line.endswith(b"\n")
    assert len(line) == p.sample_line_length(3)
    assert p.parse_line(line[:-1]) == p.Sample(0x1234, 3_000_000, (0, 512, 1023))


def test_checksum_is_crc16_ccitt_false() -> None:
    assert p.crc16(b"123456789") == 0x29B1  # the standard check value of CRC-16/CCITT-FALSE


def test_banner_and_replies_parse() -> None:
    banner = p.parse_line(p.encode_banner("1.0.0", "atmega328p", 8, 250, 500000, False, 3)[:-1])
    assert banner == p.Banner(1, "1.0.0", 8, 250, banner.fields) and banner.fields["skipped"] == "3"
    assert p.parse_line(p.encode_ok("RATE", 500)[:-1]) == p.Reply(True, "RATE", 500)
    assert p.parse_line(p.encode_ok("START")[:-1]) == p.Reply(True, "START")
    assert p.parse_line(p.encode_error("RANGE")[:-1]) == p.Reply(False, "RANGE")


def test_torn_lines_are_joined_across_feeds() -> None:
    data = b"".join(p.encode_sample(i, i * 4000, [i, 2 * i]) for i in range(5))
    decoder = p.LineDecoder(channels=2)
    messages = decoder.feed(data[:7]) + decoder.feed(data[7:51]) + decoder.feed(data[51:90]) + decoder.feed(data[90:])
    assert [m.seq for m in messages] == [0, 1, 2, 3, 4]
    assert decoder.corrupt_lines == 0 and decoder.discarded_bytes == 0


def test_first_partial_line_after_connecting_is_not_corruption() -> None:
    line = p.encode_sample(7, 1, [1, 2])
    decoder = p.LineDecoder(channels=2)
    messages = decoder.feed(line[20:] + line)
    assert [m.seq for m in messages] == [7]
    assert decoder.corrupt_lines == 0 and decoder.discarded_bytes == len(line) - 20


@pytest.mark.parametrize("damage", ["flip", "drop", "wrong_channels", "lowercase", "adc_over_range", "no_star"])
def test_damaged_lines_are_counted_and_never_emitted(damage: str) -> None:
    good = p.encode_sample(1, 2, [3, 4])
    bad = {
        "flip": good[:5] + bytes([good[5] ^ 0x01]) + good[6:],
        "drop": good[:10] + good[11:],
        "wrong_channels": p.encode_sample(1, 2, [3, 4, 5]),
        "lowercase": p.finish_line("D0000000a0000000200300a"),
        "adc_over_range": p.finish_line("D0000000100000002400003"),
        "no_star": good.replace(b"*", b"#"),
    }[damage]
    decoder = p.LineDecoder(channels=2)
    messages = decoder.feed(good + bad + good)
    assert [m.seq for m in messages] == [1, 1]
    assert decoder.corrupt_lines == 1 and decoder.discarded_bytes == len(bad)


def test_overlong_garbage_is_discarded_and_decoding_resumes() -> None:
    decoder = p.LineDecoder(channels=2)
    assert decoder.feed(p.encode_sample(1, 2, [3, 4]) + b"x" * 500) == [p.Sample(1, 2, (3, 4))]
    assert decoder.corrupt_lines == 1
    assert decoder.feed(b"\n" + p.encode_sample(2, 3, [4, 5])) == [p.Sample(2, 3, (4, 5))]


def test_random_byte_corruption_never_yields_a_wrong_sample() -> None:
    rng = np.random.default_rng(1)
    originals = [p.Sample(i, i * 4000, tuple(int(x) for x in rng.integers(0, 1024, 9))) for i in range(3000)]
    wire = bytearray(b"".join(p.encode_sample(s.seq, s.t_us, s.adc) for s in originals))
    hit = rng.random(len(wire)) < 0.02
    wire_arr = np.frombuffer(bytes(wire), dtype=np.uint8).copy()
    wire_arr[hit] ^= rng.integers(1, 256, int(hit.sum()), dtype=np.uint8)
    decoder = p.LineDecoder(channels=9)
    received = decoder.feed(wire_arr.tobytes())
    assert all(m == originals[m.seq] for m in received)
    assert 0 < decoder.corrupt_lines and len(received) + decoder.corrupt_lines >= 2000


@pytest.mark.parametrize("line, expected", [
    (b"ID", p.Command("ID")), (b"START\r", p.Command("START")), (b"STOP", p.Command("STOP")),
    (b"RATE 500", p.Command("RATE", 500)), (b"", p.Command("NONE")),
    (b"RATE", p.Command("ERR", "ARG")), (b"RATE 12a", p.Command("ERR", "ARG")), (b"RATE 123456", p.Command("ERR", "ARG")),
    (b"HELLO", p.Command("ERR", "UNKNOWN")), (b"ID*0000", p.Command("ERR", "CRC")), (b"X" * 40, p.Command("ERR", "LONG")),
])
def test_command_parsing(line: bytes, expected: p.Command) -> None:
    assert p.parse_command(line) == expected


def test_encoded_commands_carry_a_valid_checksum() -> None:
    for kind, rate in (("ID", None), ("START", None), ("STOP", None), ("RATE", 250)):
        wire = p.encode_command(kind, rate)
        assert wire.endswith(b"\n") and b"*" in wire
        assert p.parse_command(wire[:-1]) == p.Command(kind, rate)


def test_command_buffer_reports_overlong_lines() -> None:
    buffer = p.CommandBuffer()
    assert buffer.feed(b"ST") == []
    assert buffer.feed(b"ART\n" + b"Y" * 40 + b"\nID\n") == [p.Command("START"), p.Command("ERR", "LONG"), p.Command("ID")]


def test_rate_limits_follow_the_wire_and_the_adc() -> None:
    assert p.rate_fits(500, 9, 500_000) and not p.rate_fits(500, 9, 115_200)
    assert p.max_rate_hz(9, 500_000) == 854  # the ADC scan (9 x 104 us) limits before the wire does
    assert p.max_rate_hz(9, 115_200) == 230  # 50-byte lines, 10 bits per byte
    assert not p.rate_fits(0, 1, 500_000) and not p.rate_fits(1001, 1, 2_000_000)
