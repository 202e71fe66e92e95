"""The built-in simulated rig: every device simulated (same as ``sessions_template/rigs/simulated.toml``).

Rig files themselves (parsing, validation, ``RigConfig``) are ``midas_cli/devices/rigconfig.py``.
"""

from __future__ import annotations

from midas_cli.devices.rigconfig import DeviceConfig, RigConfig

SIMULATED_DEVICES = {
    "emht": "sim://emht?rate=240&sensors=4",
    "fps": "sim://fps?rate=250&channels=9",
    "video": "sim://video?rate=30",
    "handkp": "sim://handkp?rate=30",
}


def simulated_rig() -> RigConfig:
    """The built-in simulated console (same as sessions_template/rigs/simulated.toml)."""
    devices = {name: DeviceConfig(name, url, name) for name, url in SIMULATED_DEVICES.items()}
    return RigConfig("simulated", "simulated", 30.0, "all devices simulated", {}, devices, "built-in")
