"""Device URL -> backend. The one place that knows which schemes exist.

One entry per backend (``BACKENDS``): the URL scheme (and for ``sim://KIND`` the simulated kind), the
module and class that implement it, and the device kind it records (what a rig file's ``kind`` may
say). A backend's module is imported only when a URL of its scheme is built, as pyserial's
``serial_for_url`` does, so importing this module imports no backend. Adding a backend is one entry
below plus its module.

Every backend is built the same way, ``Backend(name, url, context)``: ``url`` the parsed
:class:`~midas_cli.devices.base.DeviceUrl`, ``context`` a :class:`~midas_cli.devices.base.DeviceContext`
(clock, session start, seed, session folder, and what a device carries across reconnects).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from midas_cli.devices.base import Device, DeviceContext, DeviceUrl
from midas_cli.errors import ConfigError


@dataclass(frozen=True)
class Backend:
    """One backend: ``scheme://`` (with ``sim``: ``sim://<simulated>``), the module and class that
    implement it, and the ``kind`` of device it records (the class's own ``kind``)."""

    scheme: str
    simulated: str
    module: str
    cls: str
    kind: str

    def load(self) -> type[Device]:
        """The backend class, its module imported now."""
        backend: type[Device] = getattr(importlib.import_module(self.module), self.cls)
        return backend


_SIM = "midas_cli.devices.sim.devices"
_RGBD = "midas_cli.devices.rgbd.device"
# Simulated kinds first: KINDS keeps this order (emht, fps, video, handkp, raven, lsl).
BACKENDS = (
    Backend("sim", "emht", _SIM, "SimEmHT", "emht"),
    Backend("sim", "fps", _SIM, "SimFPS", "fps"),
    Backend("sim", "video", _SIM, "SimVideoClock", "video"),
    Backend("sim", "handkp", _SIM, "SimHandKP", "handkp"),
    Backend("sim", "rgbd", _RGBD, "SimStereoDevice", "handkp"),
    Backend("fob", "", "midas_cli.devices.trakstar.driver", "FobEmHT", "emht"),
    Backend("atc3dg", "", "midas_cli.devices.trakstar.atc3dg", "Atc3dgEmHT", "emht"),
    Backend("fps", "", "midas_cli.devices.fps.driver", "FpsDevice", "fps"),
    Backend("obs", "", "midas_cli.devices.obs.device", "ObsDevice", "video"),
    Backend("raven", "", "midas_cli.devices.raven.device", "RavenDevice", "raven"),
    Backend("lsl", "", "midas_cli.devices.lsl.device", "LslDevice", "lsl"),
    Backend("uvc", "", _RGBD, "UvcStereoDevice", "handkp"),
    Backend("zed", "", _RGBD, "ZedSdkStereoDevice", "handkp"),
)
SCHEMES = tuple(dict.fromkeys(b.scheme for b in BACKENDS))
KINDS = tuple(dict.fromkeys(b.kind for b in BACKENDS))  # what a rig file's devices.<name>.kind may say
SIMULATED = {b.simulated: b for b in BACKENDS if b.scheme == "sim"}  # sim://KIND
REAL = {b.scheme: b for b in BACKENDS if b.scheme != "sim"}


def backend_entry(url: DeviceUrl) -> Backend:
    """The entry of ``url``'s backend (nothing imported); ConfigError for unknown schemes or simulated kinds."""
    if url.scheme == "sim":
        kind = url.target.strip("/")
        if kind not in SIMULATED:
            raise ConfigError(f"{url.raw}: no simulated device {kind!r} (simulated: {', '.join(SIMULATED)})")
        return SIMULATED[kind]
    if url.scheme in REAL:
        return REAL[url.scheme]
    raise ConfigError(
        f"{url.raw}: device backend {url.scheme!r}:// is not available in this version of midas "
        f"(available: {', '.join(s + '://' for s in SCHEMES)})"
    )


def backend_for(url: DeviceUrl) -> type[Device]:
    """The backend class of ``url``, its module imported; ConfigError as :func:`backend_entry`."""
    return backend_entry(url).load()


def create_device(name: str, url: str, context: DeviceContext) -> Device:
    """Build (not open) the backend for ``url``; raises ConfigError for unknown schemes or settings."""
    parsed = DeviceUrl.parse(url)
    return backend_for(parsed)(name, parsed, context)


def describe_device(name: str, url: str, seed: int = 0) -> Device:
    """A backend instance used only for its stream layout and settings (nothing is opened)."""
    return create_device(name, url, DeviceContext.describing(seed))


__all__ = ["BACKENDS", "KINDS", "Backend", "DeviceContext", "backend_entry", "backend_for", "create_device",
           "describe_device"]
