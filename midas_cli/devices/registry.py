"""Device URL -> backend. The one place that knows which schemes exist.

Every backend is built the same way, ``Backend(name, url, context)``: ``url`` the parsed
:class:`~midas_cli.devices.base.DeviceUrl`, ``context`` a :class:`~midas_cli.devices.base.DeviceContext`
(clock, session start, seed, session folder, and what a device carries across reconnects).
"""

from __future__ import annotations

from midas_cli.devices.base import KINDS, Device, DeviceContext, DeviceUrl
from midas_cli.devices.fps.driver import FpsDevice
from midas_cli.devices.lsl.device import LslDevice
from midas_cli.devices.obs.device import ObsDevice
from midas_cli.devices.raven.device import RavenDevice
from midas_cli.devices.rgbd.device import SimStereoDevice, UvcStereoDevice, ZedSdkStereoDevice
from midas_cli.devices.sim.devices import SIMULATORS
from midas_cli.devices.trakstar.atc3dg import Atc3dgEmHT
from midas_cli.devices.trakstar.driver import FobEmHT
from midas_cli.errors import ConfigError

SCHEMES = ("sim", "fob", "atc3dg", "fps", "obs", "raven", "lsl", "uvc", "zed")
BACKENDS: dict[str, type[Device]] = {"fob": FobEmHT, "atc3dg": Atc3dgEmHT, "fps": FpsDevice, "obs": ObsDevice,
                                     "raven": RavenDevice, "lsl": LslDevice, "uvc": UvcStereoDevice,
                                     "zed": ZedSdkStereoDevice}
SIM_BACKENDS: dict[str, type[Device]] = {**SIMULATORS, "rgbd": SimStereoDevice}  # sim://KIND


def backend_for(url: DeviceUrl) -> type[Device]:
    """The backend class of ``url``; ConfigError for unknown schemes or simulated kinds."""
    if url.scheme == "sim":
        kind = url.target.strip("/")
        if kind not in SIM_BACKENDS:
            raise ConfigError(f"{url.raw}: no simulated device {kind!r} (simulated: {', '.join(SIM_BACKENDS)})")
        return SIM_BACKENDS[kind]
    if url.scheme in BACKENDS:
        return BACKENDS[url.scheme]
    raise ConfigError(
        f"{url.raw}: device backend {url.scheme!r}:// is not available in this version of midas "
        f"(available: {', '.join(s + '://' for s in SCHEMES)})"
    )


def create_device(name: str, url: str, context: DeviceContext) -> Device:
    """Build (not open) the backend for ``url``; raises ConfigError for unknown schemes or settings."""
    parsed = DeviceUrl.parse(url)
    return backend_for(parsed)(name, parsed, context)


def describe_device(name: str, url: str, seed: int = 0) -> Device:
    """A backend instance used only for its stream layout and settings (nothing is opened)."""
    return create_device(name, url, DeviceContext.describing(seed))


__all__ = ["KINDS", "DeviceContext", "backend_for", "create_device", "describe_device"]
