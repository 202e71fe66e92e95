"""USB-serial latency (issue 26 item 4): the adapter behind a port, its latency timer and low-latency flag,
on fake sysfs trees laid out as the kernel lays them out; `doctor` and `rig check` through the CLI."""

from __future__ import annotations

import os
import pty
from pathlib import Path

import pytest

from midas_cli.devices import usbserial
from midas_cli.devices.usbserial import find_adapter, inspect_port, prepare_port, set_low_latency
from helpers.cli import midas

PCI = "devices/pci0000:00/0000:00:14.0/usb1"


def _link(link: Path, target: Path) -> None:
    """A relative symlink ``link`` -> ``target``, as sysfs makes them."""
    link.parent.mkdir(parents=True, exist_ok=True)
    link.symlink_to(os.path.relpath(target, link.parent))


def _usb_device(root: Path, bus_port: str, vid: str, pid: str, product: str) -> Path:
    """The USB device folder with its ids and strings (``product``: "Manufacturer Product name")."""
    usb = root / PCI / bus_port
    usb.mkdir(parents=True)
    maker, _, model = product.partition(" ")
    for name, value in (("idVendor", vid), ("idProduct", pid), ("manufacturer", maker), ("product", model)):
        (usb / name).write_text(value + "\n")
    return usb


def fake_usb_serial(root: Path, tty: str, driver: str, vid: str, pid: str, product: str,
                    latency_ms: int | None = None, latency_mode: int = 0o644) -> Path:
    """A usb-serial tty (ftdi_sio, cp210x...) under ``root``: ``class/tty/<tty>`` -> the class device in
    ``.../1-N:1.0/<tty>/tty/<tty>``, whose ``device`` link leads to the usb-serial port folder (``driver``
    link, ``latency_timer`` for FTDI), the USB device with its ids two levels up, and
    ``bus/usb-serial/devices/<tty>`` -> the port folder. Returns the port folder."""
    bus_port = f"1-{int(tty[-1]) + 2}"
    usb = _usb_device(root, bus_port, vid, pid, product)
    port = usb / f"{bus_port}:1.0" / tty
    (port / "tty" / tty).mkdir(parents=True)
    _link(port / "tty" / tty / "device", port)
    _link(root / "class" / "tty" / tty, port / "tty" / tty)
    (root / "bus" / "usb-serial" / "drivers" / driver).mkdir(parents=True, exist_ok=True)
    _link(port / "driver", root / "bus" / "usb-serial" / "drivers" / driver)
    _link(root / "bus" / "usb-serial" / "devices" / tty, port)
    if latency_ms is not None:
        (port / "latency_timer").write_text(f"{latency_ms}\n")
        (port / "latency_timer").chmod(latency_mode)
    return port


def fake_acm(root: Path, tty: str = "ttyACM0") -> None:
    """A cdc_acm tty (an Arduino's USB port): its ``device`` is the USB interface, no latency timer."""
    usb = _usb_device(root, "1-7", "2341", "0043", "Arduino Uno")
    interface = usb / "1-7:1.0"
    (interface / "tty" / tty).mkdir(parents=True)
    _link(interface / "tty" / tty / "device", interface)
    _link(root / "class" / "tty" / tty, interface / "tty" / tty)
    (root / "bus" / "usb" / "drivers" / "cdc_acm").mkdir(parents=True)
    _link(interface / "driver", root / "bus" / "usb" / "drivers" / "cdc_acm")


def fake_builtin_uart(root: Path) -> None:
    """ttyS0 on the mainboard: a platform device, no USB ids anywhere above it."""
    device = root / "devices" / "pnp0" / "00:05"
    (device / "tty" / "ttyS0").mkdir(parents=True)
    _link(device / "tty" / "ttyS0" / "device", device)
    _link(root / "class" / "tty" / "ttyS0", device / "tty" / "ttyS0")


def test_an_ftdi_at_16_ms_that_may_be_written_is_set_to_1_ms(tmp_path: Path) -> None:
    port = fake_usb_serial(tmp_path, "ttyUSB0", "ftdi_sio", "0403", "6001", "FTDI FT232R USB UART", latency_ms=16)
    report = inspect_port("/dev/ttyUSB0", tmp_path)
    assert (port / "latency_timer").read_text().strip() == "1"
    assert (report.adapter, report.driver, report.vid_pid) == ("usb", "ftdi_sio", "0403:6001")
    assert (report.latency_timer_before_ms, report.latency_timer_ms) == (16, 1)
    assert report.latency_timer_path == str(tmp_path / "bus/usb-serial/devices/ttyUSB0/latency_timer")
    assert report.note == ""
    assert report.summary() == ("/dev/ttyUSB0: USB 0403:6001 (FTDI FT232R USB UART), driver ftdi_sio, "
                                "latency timer 16 -> 1 ms")


def test_an_ftdi_timer_that_may_not_be_written_is_left_and_the_udev_rule_given(tmp_path: Path) -> None:
    port = fake_usb_serial(tmp_path, "ttyUSB1", "ftdi_sio", "0403", "6014", "FTDI FT232H", latency_ms=16,
                           latency_mode=0o444)
    report = inspect_port("/dev/ttyUSB1", tmp_path)
    assert (port / "latency_timer").read_text().strip() == "16"
    assert (report.latency_timer_before_ms, report.latency_timer_ms) == (16, 16)
    assert "echo 1 | sudo tee /sys/bus/usb-serial/devices/ttyUSB1/latency_timer" in report.note
    assert ('ACTION=="add", SUBSYSTEM=="usb-serial", DRIVER=="ftdi_sio", ATTR{latency_timer}="1"' in report.note
            and "/etc/udev/rules.d/99-midas-ftdi.rules" in report.note)
    assert "latency timer 16 ms, not 1" in report.summary()


def test_a_timer_already_at_1_ms_is_not_written(tmp_path: Path) -> None:
    port = fake_usb_serial(tmp_path, "ttyUSB0", "ftdi_sio", "0403", "6001", "FTDI FT232R", latency_ms=1,
                           latency_mode=0o444)
    report = inspect_port("/dev/ttyUSB0", tmp_path)
    assert (report.latency_timer_before_ms, report.latency_timer_ms, report.note) == (1, 1, "")
    assert (port / "latency_timer").stat().st_mode & 0o777 == 0o444


def test_a_cp210x_has_no_latency_timer_and_nothing_is_written(tmp_path: Path) -> None:
    fake_usb_serial(tmp_path, "ttyUSB0", "cp210x", "10C4", "ea60", "Silicon CP2102")
    report = inspect_port("/dev/ttyUSB0", tmp_path)
    assert (report.adapter, report.driver, report.vid_pid) == ("usb", "cp210x", "10c4:ea60")
    assert report.latency_timer_path == "" and report.latency_timer_ms is None
    assert report.summary().endswith("driver cp210x, no latency timer")


def test_a_cdc_acm_port_and_a_by_id_link_are_followed(tmp_path: Path) -> None:
    sysfs = tmp_path / "sys"
    fake_acm(sysfs)
    by_id = tmp_path / "serial" / "by-id" / "usb-Arduino_Uno-if00"
    by_id.parent.mkdir(parents=True)
    by_id.symlink_to("/dev/ttyACM0")
    report = find_adapter(str(by_id), sysfs)
    assert (report.adapter, report.driver, report.vid_pid, report.tty) == ("usb", "cdc_acm", "2341:0043", "ttyACM0")
    assert usbserial.adapter_ports(sysfs) == ["/dev/ttyACM0"]


def test_ptys_urls_and_builtin_uarts_are_not_usb_adapters(tmp_path: Path) -> None:
    fake_builtin_uart(tmp_path)
    assert find_adapter("/dev/ttyS0", tmp_path).note == "not a USB serial adapter"
    assert find_adapter("socket://localhost:7000", tmp_path).note == "not a local serial port (a URL)"
    controller, terminal = pty.openpty()
    try:
        name = os.ttyname(terminal)
        link = tmp_path / "emulator-port"
        link.symlink_to(name)
        report = prepare_port(str(link), terminal, tmp_path)
        assert (report.adapter, report.note) == ("not usb", "not a USB serial adapter (a pseudo-terminal)")
        assert report.low_latency == "unsupported"
        assert report.summary() == f"{link}: not a USB serial adapter (a pseudo-terminal), low-latency flag unsupported"
    finally:
        os.close(controller)
        os.close(terminal)


def test_links_out_of_the_tree_and_garbage_values_are_reported_not_trusted(tmp_path: Path) -> None:
    sysfs = tmp_path / "sys"
    port = fake_usb_serial(sysfs, "ttyUSB0", "ftdi_sio", "0403", "6001", "FTDI", latency_ms=16)
    (port / "latency_timer").write_text("sixteen\n")
    (port.parents[1] / "idVendor").write_text("../../etc\n")
    report = inspect_port("/dev/ttyUSB0", sysfs)
    assert report.vid_pid == "?:6001" and report.latency_timer_ms is None
    assert (port / "latency_timer").read_text() == "sixteen\n"  # an unknown value is not overwritten
    elsewhere = tmp_path / "elsewhere" / "ttyUSB3"
    elsewhere.mkdir(parents=True)
    (elsewhere / "idVendor").write_text("0403\n")
    (elsewhere / "idProduct").write_text("6001\n")
    _link(sysfs / "class" / "tty" / "ttyUSB3" / "device", elsewhere)
    assert find_adapter("/dev/ttyUSB3", sysfs).adapter == "not usb"
    assert find_adapter("/dev/ttyUSB0", tmp_path / "nothing").adapter == "unknown"


def test_the_low_latency_flag_is_set_through_the_serial_ioctls(monkeypatch: pytest.MonkeyPatch) -> None:
    """A tty driver that supports TIOCSSERIAL keeps the flag; one that drops it reads back "off"."""
    import termios

    for keeps, expected in ((True, "on"), (False, "off")):
        flags = {"value": 0x40}

        def ioctl(fd: int, request: int, buffer, keeps: bool = keeps, flags: dict = flags) -> None:
            if request == termios.TIOCGSERIAL:
                buffer[usbserial.SERIAL_FLAGS_INDEX] = flags["value"]
            elif keeps:
                flags["value"] = buffer[usbserial.SERIAL_FLAGS_INDEX]

        monkeypatch.setattr(usbserial.fcntl, "ioctl", ioctl)
        assert set_low_latency(7) == expected
        assert flags["value"] == (0x40 | usbserial.ASYNC_LOW_LATENCY if keeps else 0x40)
    assert set_low_latency(None) is None


def test_doctor_lists_every_adapter_of_a_fake_sysfs_and_sets_the_ftdi_timer(tmp_path: Path) -> None:
    port = fake_usb_serial(tmp_path, "ttyUSB0", "ftdi_sio", "0403", "6001", "FTDI FT232R", latency_ms=16)
    fake_usb_serial(tmp_path, "ttyUSB1", "ftdi_sio", "0403", "6010", "FTDI FT2232H", latency_ms=16,
                    latency_mode=0o444)
    fake_usb_serial(tmp_path, "ttyUSB2", "cp210x", "10c4", "ea60", "Silicon CP2102")
    fake_acm(tmp_path)
    fake_builtin_uart(tmp_path)
    result = midas("doctor", "--obs-port", "1", env={usbserial.SYSFS_ROOT_ENV: str(tmp_path)}, check=True)
    usb = [line for line in result.stdout.splitlines() if line.startswith("USB serial adapter")]
    assert [line.split(":")[0] for line in usb] == [f"USB serial adapter /dev/{tty}"
                                                   for tty in ("ttyACM0", "ttyUSB0", "ttyUSB1", "ttyUSB2")]
    assert usb[1].endswith("driver ftdi_sio, latency timer 16 -> 1 ms")
    assert (port / "latency_timer").read_text().strip() == "1"
    assert "latency timer 16 ms, not 1" in usb[2] and "99-midas-ftdi.rules" in usb[2]
    assert usb[3].endswith("driver cp210x, no latency timer")


def test_doctor_json_carries_each_adapter_report(tmp_path: Path) -> None:
    from midas_cli.diagnostics import usb_serial_adapters

    fake_usb_serial(tmp_path, "ttyUSB0", "ftdi_sio", "0403", "6001", "FTDI FT232R", latency_ms=16)
    (adapter,) = usb_serial_adapters(tmp_path)
    assert {k: adapter[k] for k in ("port", "adapter", "driver", "vid_pid", "latency_timer_before_ms",
                                    "latency_timer_ms", "low_latency")} == {
        "port": "/dev/ttyUSB0", "adapter": "usb", "driver": "ftdi_sio", "vid_pid": "0403:6001",
        "latency_timer_before_ms": 16, "latency_timer_ms": 1, "low_latency": None}
    assert usb_serial_adapters(tmp_path / "no-sysfs") == []


def test_rig_check_on_an_emulator_pty_reports_it_is_not_a_usb_adapter(tmp_path: Path) -> None:
    from midas_cli.devices.fps.emulator import FpsEmulator, FpsEmulatorConfig
    from midas_cli.devices.rigconfig import load_rig
    from midas_cli.record.rigcheck import check_rig

    with FpsEmulator(FpsEmulatorConfig(channels=2)) as emulator:
        rig = tmp_path / "rig.toml"
        rig.write_text(f'[rig]\nname = "pedals"\nplatform = "davinci-xi"\n\n'
                       f'[devices.fps]\nurl = "fps://{emulator.path}?channels=2"\n')
        text = midas("rig", "check", str(rig), "--seconds", "0.5", cwd=tmp_path)
        (checked,) = check_rig(load_rig(rig), 0.3)
    assert text.returncode == 0, text.stderr
    assert (f"fps serial port: {emulator.path}: not a USB serial adapter (a pseudo-terminal), "
            f"low-latency flag unsupported") in text.stdout
    assert checked.state == "ok", checked.error
    assert checked.as_dict()["info"]["usb_serial"]["adapter"] == "not usb"
    assert checked.as_dict()["info"]["usb_serial"]["low_latency"] == "unsupported"


# -- read_available: the drivers' read of a port's descriptor ---------------------------------------
def test_read_available_takes_everything_waiting_waits_at_most_its_timeout_and_raises_when_the_port_goes() -> None:
    import serial

    master, slave = pty.openpty()
    port = serial.Serial(os.ttyname(slave), timeout=0.005)
    fd = usbserial.port_fd(port)
    try:
        assert fd is not None
        os.write(master, b"A,1\r\n" * 300)  # 1500 bytes waiting: one call takes them all
        got = b""
        while len(got) < 1500:
            chunk = usbserial.read_available(port, fd, 1.0)
            assert chunk, "data was waiting"
            got += chunk
        assert got == b"A,1\r\n" * 300
        assert usbserial.read_available(port, fd, 0.01) == b""  # nothing more: b'' once the timeout passes
        os.close(master)  # the device side vanishes: an error the drivers turn into "lost", never b'' forever
        master = -1
        with pytest.raises((OSError, serial.SerialException)):
            usbserial.read_available(port, fd, 1.0)
    finally:
        port.close()
        os.close(slave)
        if master >= 0:
            os.close(master)


def test_read_available_falls_back_to_pyserial_for_ports_without_a_descriptor() -> None:
    import serial

    port = serial.serial_for_url("loop://", timeout=0.005)
    try:
        assert usbserial.port_fd(port) is None
        port.write(b"hello")
        assert usbserial.read_available(port, None, 0.005) == b"hello"
        assert usbserial.read_available(port, None, 0.005) == b""
    finally:
        port.close()
