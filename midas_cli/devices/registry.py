"""Device URL -> backend. The one place that knows which schemes exist."""

from __future__ import annotations

from midas_cli.clock import HostClock
from midas_cli.devices.base import KINDS, Device, DeviceUrl
from midas_cli.devices.sim.devices import SIMULATORS
from midas_cli.errors import ConfigError

SCHEMES = ("sim",)


def create_device(name: str, url: str, clock: HostClock, start_ns: int, seed: int = 0) -> Device:
    """Build (not open) the backend for ``url``; raises ConfigError for unknown schemes or settings."""
    parsed = DeviceUrl.parse(url)
    if parsed.scheme == "sim":
        kind = parsed.target.strip("/")
        if kind not in SIMULATORS:
            raise ConfigError(f"{url}: no simulated device {kind!r} (simulated: {', '.join(SIMULATORS)})")
        return SIMULATORS[kind](name, parsed, clock, start_ns, seed)
    raise ConfigError(
        f"{url}: device backend {parsed.scheme!r}:// is not available in this version of midas "
        f"(available: {', '.join(s + '://' for s in SCHEMES)})"
    )


def describe_device(name: str, url: str, seed: int = 0) -> Device:
    """A backend instance used only for its stream layout and settings (nothing is opened)."""
    return create_device(name, url, HostClock(0), 0, seed)


__all__ = ["KINDS", "create_device", "describe_device"]
