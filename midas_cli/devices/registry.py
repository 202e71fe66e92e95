"""Device URL -> backend. The one place that knows which schemes exist."""

from __future__ import annotations

from midas_cli.clock import HostClock
from midas_cli.devices.base import KINDS, Device, DeviceUrl
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
BACKENDS = {"fob": FobEmHT, "atc3dg": Atc3dgEmHT, "fps": FpsDevice}
# backends built with (name, url, clock, session_dir): they write files into the session
SESSION_BACKENDS = {"raven": RavenDevice, "lsl": LslDevice, "uvc": UvcStereoDevice, "zed": ZedSdkStereoDevice}


def create_device(name: str, url: str, clock: HostClock, start_ns: int, seed: int = 0,
                  session_dir: str = "") -> Device:
    """Build (not open) the backend for ``url``; raises ConfigError for unknown schemes or settings.
    ``session_dir`` (absolute) is for backends that write files into the session (obs:// video/)."""
    parsed = DeviceUrl.parse(url)
    if parsed.scheme == "sim":
        kind = parsed.target.strip("/")
        if kind == "rgbd":
            return SimStereoDevice(name, parsed, clock, start_ns, seed, session_dir)
        if kind not in SIMULATORS:
            raise ConfigError(f"{url}: no simulated device {kind!r} (simulated: {', '.join(SIMULATORS)})")
        return SIMULATORS[kind](name, parsed, clock, start_ns, seed)
    if parsed.scheme in BACKENDS:
        return BACKENDS[parsed.scheme](name, parsed, clock, start_ns, seed)
    if parsed.scheme == "obs":
        return ObsDevice(name, parsed, clock, session_dir)
    if parsed.scheme in SESSION_BACKENDS:
        return SESSION_BACKENDS[parsed.scheme](name, parsed, clock, session_dir)
    raise ConfigError(
        f"{url}: device backend {parsed.scheme!r}:// is not available in this version of midas "
        f"(available: {', '.join(s + '://' for s in SCHEMES)})"
    )


def describe_device(name: str, url: str, seed: int = 0) -> Device:
    """A backend instance used only for its stream layout and settings (nothing is opened)."""
    return create_device(name, url, HostClock(0), 0, seed)


__all__ = ["KINDS", "create_device", "describe_device"]
