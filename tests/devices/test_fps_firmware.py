"""The firmware: its protocol code compiled for this computer matches the Python codec byte for byte,
and the whole firmware builds with avr-gcc (CI installs gcc-avr, avr-libc)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from midas_cli.devices.fps import protocol as p
from helpers.cli import REPO

FIRMWARE = REPO / "firmware" / "fps"


@pytest.fixture(scope="module")
def harness(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("gcc") is None or shutil.which("make") is None:
        pytest.skip("gcc/make not installed: cannot build the host-side protocol harness")
    build = tmp_path_factory.mktemp("fps-host")
    subprocess.run(["make", "-C", str(FIRMWARE), "host-harness", f"BUILD={build}"], check=True, capture_output=True)
    return build / "host_harness"


def _run(harness: Path, requests: list[str]) -> bytes:
    result = subprocess.run([str(harness)], input=("\n".join(requests) + "\n").encode(), capture_output=True,
                            check=True, timeout=30)
    return result.stdout


def test_sample_lines_match_byte_for_byte(harness: Path) -> None:
    rng = np.random.default_rng(3)
    cases = [(0, 0, [0]), (2**32 - 1, 2**32 - 1, [1023] * 9)]
    cases += [(int(rng.integers(0, 2**32)), int(rng.integers(0, 2**32)),
               [int(a) for a in rng.integers(0, 1024, int(rng.integers(1, 10)))]) for _ in range(300)]
    requests = [f"sample {seq} {t} " + " ".join(map(str, adc)) for seq, t, adc in cases]
    assert _run(harness, requests) == b"".join(p.encode_sample(seq, t, adc) for seq, t, adc in cases)


def test_banner_and_replies_match_byte_for_byte(harness: Path) -> None:
    requests = ["banner 1.0.0 atmega328p 8 250 500000 0 0", "banner 2.1.3 atmega2560 9 1000 1000000 1 4294967295",
                "ok START", "ok STOP", "ok RATE 1", "ok RATE 854"] + [f"err {code}" for code in range(1, 6)]
    expected = [p.encode_banner("1.0.0", "atmega328p", 8, 250, 500000, False, 0),
                p.encode_banner("2.1.3", "atmega2560", 9, 1000, 1000000, True, 2**32 - 1),
                p.encode_ok("START"), p.encode_ok("STOP"), p.encode_ok("RATE", 1), p.encode_ok("RATE", 854)]
    expected += [p.encode_error(name) for name in p.ERROR_NAMES[1:]]
    assert _run(harness, requests) == b"".join(expected)


def _python_command(command: p.Command) -> str:
    if command.kind == "RATE":
        return f"RATE {command.arg}"
    if command.kind == "ERR":
        return f"ERR {p.ERROR_NAMES.index(command.arg)}"
    return command.kind


def test_command_parser_agrees_on_good_bad_and_random_lines(harness: Path) -> None:
    rng = np.random.default_rng(5)
    lines = [b"ID", b"START\r", b"STOP", b"RATE 250", b"RATE 00500", b"RATE", b"RATE x", b"RATE 123456", b"",
             b"id", b"ID*0000", b"*", b"X" * 31, b"X" * 32, b"Y" * 40, b"RATE 9\r\r"]
    lines += [p.encode_command(k, r)[:-1] for k, r in (("ID", None), ("RATE", 77), ("STOP", None))]
    lines += [p.encode_command("RATE", 300)[:-1].lower()]
    alphabet = np.frombuffer(b"IDSTARTOPE 0123456789*\r\x00", dtype=np.uint8)
    lines += [rng.choice(alphabet, int(rng.integers(0, 12))).tobytes() for _ in range(400)]
    lines = [line for line in lines if b"\n" not in line]
    requests = [f"cmd {line.hex()}" for line in lines]
    expected = "".join(_python_command(p.parse_command(line)) + "\n" for line in lines)
    assert _run(harness, requests).decode() == expected
    stream = b"\n".join(lines) + b"\n"
    fed = _run(harness, [f"feed {stream[i:i + 200].hex()}" for i in range(0, len(stream), 200)])
    assert fed.decode().count("\n") > 0  # the line buffer is checked against the Python one below
    python_fed = "".join(_python_command(c) + "\n" for i in range(0, len(stream), 200)
                         for c in p.CommandBuffer().feed(stream[i:i + 200]))
    assert fed.decode() == python_fed


def test_rate_rule_agrees(harness: Path) -> None:
    cases = [(r, c, b) for r in (1, 30, 230, 231, 500, 854, 855, 1000, 1001) for c in (1, 6, 9) for b in (115200, 500000)]
    output = _run(harness, [f"fits {r} {c} {b}" for r, c, b in cases]).decode().split()
    assert output == [str(int(p.rate_fits(r, c, b))) for r, c, b in cases]


@pytest.mark.parametrize("mcu, arch", [("atmega328p", "avr:5"), ("atmega2560", "avr:6")])
def test_firmware_builds_with_avr_gcc(tmp_path: Path, mcu: str, arch: str) -> None:
    if shutil.which("avr-gcc") is None or shutil.which("make") is None:
        pytest.skip("avr-gcc not installed (Debian/Ubuntu: apt-get install gcc-avr avr-libc binutils-avr)")
    result = subprocess.run(["make", "-C", str(FIRMWARE), f"MCU={mcu}", f"BUILD={tmp_path}"], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    hex_file = (tmp_path / "fps.hex").read_text()
    assert hex_file.startswith(":") and hex_file.rstrip().endswith(":00000001FF")  # Intel HEX end record
    strings = subprocess.run(["avr-objcopy", "-O", "binary", "-j", ".data", str(tmp_path / "fps.elf"),
                              str(tmp_path / "data.bin")], capture_output=True)
    assert strings.returncode == 0 and b"#MIDAS-FPS" in (tmp_path / "data.bin").read_bytes()
    header = subprocess.run(["avr-objdump", "-f", str(tmp_path / "fps.elf")], capture_output=True, text=True)
    assert f"architecture: {arch}" in header.stdout
