"""The FOB RS-232 codec on byte strings: words, records, commands, torn and corrupted frames."""

from __future__ import annotations

import numpy as np
import pytest

from midas_cli.devices.trakstar import protocol as fob

VALUES = np.array([[100.0, -50.0, 250.0, 45.0, -30.0, 170.0],
                   [-300.0, 20.0, 0.0, -179.0, 89.0, 0.0]])


def _records(values: np.ndarray = VALUES, range_in: int = 36) -> list[bytes]:
    words = fob.words_from_values(values, range_in)
    return [fob.encode_record(w, address) for address, w in enumerate(words, start=1)]


def test_word_formula_and_scaling_follow_the_protocol() -> None:
    # x word 0x4000 -> msb 0x20, lsb 0x00: value = 16384 * 36 in / 32768 = 18 in = 457.2 mm
    data = bytes([0x80, 0x20] + [0x00, 0x00] * 3 + [0x00, 0x60] + [0x00, 0x00])
    words = fob.decode_words(data)
    assert words[0] == 0x4000 and words[4] == -0x4000
    values = fob.values_from_words(np.array(words), 36)
    assert values[0] == pytest.approx(457.2) and values[4] == pytest.approx(-90.0)
    assert fob.values_from_words(np.array(words), 72)[0] == pytest.approx(914.4)


def test_encoded_record_has_phasing_bit_only_on_first_byte_and_address_last() -> None:
    record = _records()[1]
    assert len(record) == fob.RECORD_BYTES
    assert record[0] & 0x80 and not any(b & 0x80 for b in record[1:])
    assert record[-1] == 2


def test_round_trip_is_exact_to_the_14_bit_resolution() -> None:
    decoder = fob.RecordDecoder(sensors=2, range_in=36)
    stream = b"".join(_records() * 2)  # two cycles; the second's first byte confirms the first's framing
    records = decoder.feed(stream, 123)
    assert [r.address for r in records] == [1, 2, 1]
    expected = fob.values_from_words(fob.words_from_values(VALUES, 36), 36)
    assert np.allclose(records[0].values, expected[0]) and np.allclose(records[1].values, expected[1])
    assert abs(records[0].values[0] - 100.0) <= 36 * 25.4 / 32768 * 2  # quantisation step 0.11 mm
    assert decoder.counts.discarded_bytes == 0


def test_angles_wrap_and_positions_outside_range_are_refused() -> None:
    words = fob.words_from_values(np.array([0, 0, 0, 190.0, 0, -185.0]), 36)
    assert fob.values_from_words(words, 36)[3] == pytest.approx(-170.0, abs=0.03)
    with pytest.raises(ValueError, match="range"):
        fob.words_from_values(np.array([1000.0, 0, 0, 0, 0, 0]), 36)


def test_torn_frames_fed_byte_by_byte_decode_the_same() -> None:
    stream = b"".join(_records() * 3)
    decoder = fob.RecordDecoder(sensors=2, range_in=36)
    out = []
    for i, byte in enumerate(stream):
        out += decoder.feed(bytes([byte]), i)
    assert len(out) == 5  # the last record waits for the next record's first byte
    assert out[0].t_host_ns == fob.RECORD_BYTES - 1, "time of the byte that completed the record"


def test_decoder_resynchronises_after_garbage_and_lost_bytes() -> None:
    a, b = _records()
    lost = a[:5] + a[6:]  # a byte lost inside record 1
    stream = b"\x01\x02\x7f" + lost + b + a + b + a
    decoder = fob.RecordDecoder(sensors=2, range_in=36)
    records = decoder.feed(stream, 0)
    assert [r.address for r in records] == [2, 1, 2]
    assert decoder.counts.discarded_bytes == 3 + 12
    assert records[0].discarded_before == 15


@pytest.mark.parametrize("position", range(fob.RECORD_BYTES))
def test_a_phasing_breaking_byte_anywhere_never_yields_a_wrong_record(position: int) -> None:
    a, b = _records()
    broken = bytearray(b)
    broken[position] ^= 0x80
    stream = a + bytes(broken) + a + b + a
    records = fob.RecordDecoder(sensors=2, range_in=36).feed(stream, 0)
    good = fob.RecordDecoder(sensors=2, range_in=36).feed(a + b, 0)[0]
    expected = {1: good.values, 2: fob.RecordDecoder(sensors=2, range_in=36).feed(b + a, 0)[0].values}
    for record in records:
        assert record.values == expected[record.address]
    assert [r.address for r in records][-2:] == [1, 2]


def test_bad_address_and_impossible_elevation_are_rejected() -> None:
    a, b = _records()
    wrong_address = a[:-1] + bytes([9])
    words = fob.words_from_values(VALUES[0], 36).astype(np.int64)
    words[4] = 0x6000  # elevation 135 deg
    impossible = fob.encode_record(words, 1)
    decoder = fob.RecordDecoder(sensors=2, range_in=36)
    records = decoder.feed(wrong_address + impossible + b + a, 0)
    assert [r.address for r in records] == [2]
    assert decoder.counts.reasons["address out of range"] == 1
    assert decoder.counts.reasons["elevation out of range"] == 1


def _record(address: int, discarded: int = 0) -> fob.Record:
    return fob.Record(address, (float(address),) * 6, address, discarded)


def test_groups_leave_missing_sensors_empty_and_count_them() -> None:
    assembler = fob.GroupAssembler(sensors=4)
    groups = assembler.add([_record(1), _record(2), _record(4, discarded=13), _record(1), _record(2)])
    assert len(groups) == 1 and groups[0].index == 0
    assert groups[0].values[2] is None and groups[0].values[3] == (4.0,) * 6
    groups = assembler.add([_record(1)])
    assert groups[0].index == 1 and groups[0].values[2:] == (None, None)
    assert assembler.missing == 1 + 2


def test_a_whole_lost_cycle_shows_as_an_index_gap_not_a_merged_row() -> None:
    assembler = fob.GroupAssembler(sensors=4)
    # cycle 0 sensors 1-2, then sensors 3, 4 of cycle 0 and 1, 2 of cycle 1 lost (52 bytes), then 3, 4
    groups = assembler.add([_record(1), _record(2), _record(3, discarded=4 * 13), _record(4)])
    assert [g.index for g in groups] == [0, 1]
    assert groups[1].values[:2] == (None, None) and groups[0].values[2:] == (None, None)
    lost_cycle = assembler.add([_record(1, discarded=4 * 13), _record(2), _record(3), _record(4)])
    assert [g.index for g in lost_cycle] == [3]


def test_commands_and_replies() -> None:
    assert fob.change_word(fob.PARAM_MEASUREMENT_RATE, fob.rate_word(200.0)) == b"P\x07\x00\xc8"
    assert fob.change_byte(fob.PARAM_GROUP_MODE, 1) == b"P\x23\x01"
    assert fob.change_byte(fob.PARAM_AUTOCONFIG, 4) == b"P\x32\x04"
    assert fob.examine(fob.PARAM_POSITION_SCALING) == b"O\x03"
    assert fob.to_sensor(3) + fob.POSITION_ANGLES == b"\xf3Y"
    assert fob.parse_reply(fob.PARAM_MEASUREMENT_RATE, b"\x00\xc8") == 200 * 256
    with pytest.raises(ValueError):
        fob.parse_reply(fob.PARAM_MEASUREMENT_RATE, b"\x00")
    with pytest.raises(ValueError):
        fob.rate_word(300.0)


def test_line_capacity_matches_the_design_figure() -> None:
    assert fob.line_capacity_hz(115200, 4) == pytest.approx(221.5, abs=0.1)
