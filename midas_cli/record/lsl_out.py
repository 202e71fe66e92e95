"""`midas record --lsl-out`: every stream is also published live as an LSL outlet while it is recorded.

It lives in the device worker (record/worker.py ``WorkerOutput.write``), not in the recorder: the
worker holds the rows the moment they are on disk, in the device's own process, while the recorder
gets bookkeeping only (sequence numbers and times, by design: no row crosses a process between the
device read and the disk). Publishing from the worker adds no process hop, and a slow or failing
outlet can only ever touch its own device's worker.

The crash-safety contract holds: rows are appended to their file first, their bookkeeping sent next,
and only then pushed to the outlet, so a consumer never sees a sample that is not on disk. Pushing is
non-blocking in liblsl (it queues for each consumer). Any failure (liblsl missing, an outlet that
cannot be created, a push that raises) is one ``warning`` event for the live screen and
logs/midas.log, and that stream is no longer published; the recording goes on untouched.

The outlets are those of `midas replay` (devices/lsl/outlet.py): name, device kind as type, labels,
units and nominal rate from the stream's spec, ``source_id`` ``midas:<session folder>:<stream>``; each
sample's timestamp is its ``t_host_ns`` on the local LSL clock, ``(t_host_ns - anchor_ns) / 1e9``.
An outlet is announced when its stream's first rows arrive. The operator's markers are written by the
recorder, not a worker: the recorder holds one more ``LiveOutlets`` for them (record/markers.py
``MarkerLog(publish=...)``, made in commands/record_control.py), pushing each marker once it is fsynced.
"""

from __future__ import annotations

from typing import Any, Callable

from midas_cli.devices.lsl.device import import_pylsl
from midas_cli.devices.lsl.outlet import lsl_config_file, lsl_seconds, open_outlet, row_values
from midas_cli.session.schema import StreamSpec


def lsl_out_manifest(enabled: bool) -> dict[str, Any]:
    """The manifest's ``lsl_out``: whether every stream was also published as an LSL outlet (listening
    on every network interface), and the liblsl configuration file that applied (None: its defaults)."""
    if not enabled:
        return {"enabled": False}
    config = lsl_config_file()
    return {"enabled": True, "lsl_config": None if config is None else str(config)}


class LiveOutlets:
    """One worker's outlets, made on demand; ``warn(message)`` reports a stream that stopped publishing."""

    def __init__(self, session: str, kind: str, anchor_ns: int, warn: Callable[[str], None]) -> None:
        self.session, self.kind, self.anchor_ns, self.warn = session, kind, anchor_ns, warn
        self.outlets: dict[str, Any] = {}
        self.failed: set[str] = set()
        try:
            import_pylsl()  # now, not on the first rows' path: loading liblsl takes a while
        except Exception as exc:  # noqa: BLE001 - reported; recording goes on
            self.failed.add("*")
            warn(f"--lsl-out: nothing is published: {exc}")

    def publish(self, spec: StreamSpec, rows: list[tuple]) -> None:
        """Push ``rows`` (seq, t_host_ns, ..., already on disk) to the stream's outlet; never raises."""
        if "*" in self.failed or spec.name in self.failed or not rows:
            return
        try:
            outlet = self.outlets.get(spec.name)
            if outlet is None:
                outlet = self.outlets[spec.name] = open_outlet(spec, self.kind, self.session)
            outlet.push_chunk(row_values(spec, rows), [lsl_seconds(row[1], self.anchor_ns) for row in rows])
        except Exception as exc:  # noqa: BLE001 - publishing must never end a recording: reported, then off
            self.failed.add(spec.name)
            self.outlets.pop(spec.name, None)
            self.warn(f"--lsl-out: stream {spec.name} is no longer published ({type(exc).__name__}: {exc}); "
                      f"recording goes on")

    def close(self) -> None:
        self.outlets.clear()  # pylsl closes an outlet when its object goes
