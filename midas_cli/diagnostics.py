"""Facts for `midas doctor` and bug reports: versions, serial ports and their USB adapters, OBS
reachability, GPU, disk; and the repairs doctor makes: a USB-serial adapter's latency timer is set to
1 ms where permitted (``usb_serial_adapters``), OBS settings a killed midas left changed are put back
(``restore_obs_settings``)."""

from __future__ import annotations

import importlib.metadata
import platform
import shutil
import socket
import sys
from pathlib import Path
from typing import Any

from midas_cli import __version__
from midas_cli.record.priority import high_permitted

PACKAGES = ("typer", "rich", "pyserial", "numpy", "pandas", "scipy", "opencv-python-headless", "obsws-python",
            "torch")
TOOLS = ("tmux", "ffprobe", "obs", "avr-gcc")


def collect(obs_host: str = "localhost", obs_port: int = 4455, disk_path: Path = Path(".")) -> dict[str, Any]:
    return {
        "midas": __version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "packages": {name: _package_version(name) for name in PACKAGES},
        "tools": {name: shutil.which(name) for name in TOOLS},
        "serial_ports": _serial_ports(),
        "usb_serial": usb_serial_adapters(),
        "high_priority": high_permitted(),  # may `record --priority high` give the workers nice -10
        "obs_websocket": _tcp_reachable(obs_host, obs_port),
        "gpu": _gpu(),
        "disk_free_bytes": shutil.disk_usage(disk_path if disk_path.exists() else Path(".")).free,
    }


def _package_version(name: str) -> str | None:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def _serial_ports() -> list[dict[str, str]]:
    from serial.tools import list_ports

    return [{"device": p.device, "description": p.description, "hwid": p.hwid} for p in list_ports.comports()]


def usb_serial_adapters(sysfs: Path | None = None) -> list[dict[str, Any]]:
    """Every ``/dev/ttyUSB*`` and ``/dev/ttyACM*`` in sysfs (``sysfs``, else $MIDAS_SYSFS_ROOT, else /sys):
    its adapter, with the latency timer set to 1 ms where permitted (the ports are not opened)."""
    from midas_cli.devices.usbserial import adapter_ports, inspect_port

    return [inspect_port(port, sysfs).as_dict() for port in adapter_ports(sysfs)]


def _tcp_reachable(host: str, port: int) -> dict[str, Any]:
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return {"address": f"{host}:{port}", "reachable": True}
    except OSError as exc:
        return {"address": f"{host}:{port}", "reachable": False, "error": exc.strerror or str(exc)}


def _gpu() -> dict[str, Any]:
    try:
        import torch
    except ImportError:
        return {"torch": False, "cuda": False}
    if not torch.cuda.is_available():
        return {"torch": True, "cuda": False}
    names = [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]
    return {"torch": True, "cuda": True, "devices": names}


def restore_obs_settings(directory: Path | None = None, timeout_s: float = 3.0) -> list[dict[str, Any]]:
    """Every saved copy of OBS settings (``$XDG_STATE_HOME/midas/obs-settings-*.json``) whose midas is
    gone: put the values back into that OBS (password from the file or variable the copy names, else
    MIDAS_OBS_PASSWORD), stop the recording it left running into its session, delete the copy. One entry
    per copy: ``status`` "restored", "in use" (its midas is still running) or "not restored" (``error``
    says why; the copy is kept)."""
    from midas_cli.clock import HostClock
    from midas_cli.devices.obs.connection import ObsConnection, resolve_password
    from midas_cli.devices.obs.profile import recover_stale
    from midas_cli.devices.obs.saved import SettingsStore, load_copy
    from midas_cli.errors import MidasError

    results = []
    for path in SettingsStore.all_copies(directory):
        entry: dict[str, Any] = {"file": str(path)}
        try:
            saved = load_copy(path)
            if saved is None:  # deleted meanwhile
                continue
            entry["obs"] = saved.obs
            if saved.owner() != "stale":
                entry.update(status="in use", owner_pid=saved.owner_pid)
                results.append(entry)
                continue
            host, _, port = saved.obs.rpartition(":")
            password, _ = resolve_password(saved.password_env, saved.password_file)
            connection = ObsConnection(host, int(port), password, timeout_s, HostClock.anchored_now())
            try:
                store = SettingsStore(host, int(port), path=path)
                entry.update(status="restored", message=recover_stale(connection, store))
            finally:
                connection.close()
        except MidasError as exc:
            entry.update(status="not restored", error=str(exc))
        results.append(entry)
    return results
