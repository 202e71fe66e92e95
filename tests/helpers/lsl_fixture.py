"""Keep LSL discovery on this host for tests: a loopback-only liblsl configuration and a test outlet."""

from __future__ import annotations

import os
import threading
import time
import uuid
from pathlib import Path

LSL_CONFIG = """[ports]
IPv6 = disable
[multicast]
ResolveScope = machine
[lab]
KnownPeers = {{127.0.0.1}}
SessionID = {session}
"""

_CONFIG: list[Path] = []


def loopback_lsl_config(folder: Path) -> Path:
    """Write an lsl_api.cfg that resolves only on this machine, in a session of its own, and point
    LSLAPICFG at it (liblsl reads it once per process: call before pylsl is first used; subprocesses
    inherit the variable). Once per test process: later calls return the first file."""
    if _CONFIG:  # liblsl has read the first one already: every later test must use the same
        return _CONFIG[0]
    path = folder / "lsl_api.cfg"
    _CONFIG.append(path)
    path.write_text(LSL_CONFIG.format(session=f"midas-test-{uuid.uuid4().hex[:12]}"), encoding="utf-8")
    os.environ["LSLAPICFG"] = str(path)
    return path


class CounterOutlet:
    """An LSL outlet sending ``rate`` samples/s of 3 channels: counter, sin, cos (labels in <desc>).
    ``pushed`` keeps (counter, timestamp) of every sample."""

    def __init__(self, name: str, rate: float = 100.0, stream_type: str = "Test") -> None:
        import pylsl

        info = pylsl.StreamInfo(name, stream_type, 3, rate, "double64", f"midas-test-{name}")
        channels = info.desc().append_child("channels")
        for label in ("counter", "sine", "cosine"):
            channels.append_child("channel").append_child_value("label", label)
        self.outlet = pylsl.StreamOutlet(info)
        self.rate = rate
        self.pushed: list[tuple[int, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> "CounterOutlet":
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=2)

    def _run(self) -> None:
        import math
        import pylsl

        start = time.monotonic()
        k = 0
        while not self._stop.is_set():
            if time.monotonic() < start + k / self.rate:
                time.sleep(0.002)
                continue
            stamp = pylsl.local_clock()
            self.outlet.push_sample([float(k), math.sin(k / 10), math.cos(k / 10)], stamp)
            self.pushed.append((k, stamp))
            k += 1
