"""The session's sync statement: how its streams were synchronised, in the words a dataset collection asks
for (the Open-H-Embodiment collection requires one with every contributed dataset).

Written into the manifest when a recording is finalised (``manifest["sync"]``: the method, each
stream's clocks and each device worker's scheduling priority) and assembled in full on demand
(``statement``): the same, plus what was measured later, each stream's fit of host stamps against its
device clock (drift, jitter; `midas align`, analysis/clockfit.py) and the offsets between modalities
(`midas eval sync`). Exports carry the full statement (Parquet schema metadata ``midas.sync``;
`session info --json` shows it).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

METHOD = ("software timestamping on one clock: every sample of every stream is stamped t_host_ns, the "
          "recording host's CLOCK_MONOTONIC (anchored to the Unix epoch at the session start, immune to NTP "
          "steps), when its bytes are read from the device; no hardware trigger; device clocks are kept as "
          "recorded, never used to move a stamp")
SIMULATED = ("simulated: `midas simulate dataset` generated every t_host_ns (true time plus modelled sensor "
             "latency, delays and jitter; see the rig entry and calib/ground_truth.json)")
IMPORTED = ("imported: the original system's timestamps converted to t_host_ns by `midas import` (see the rig's "
            "import_report); how that system synchronised its streams is its own")
NOT_MEASURED = "not measured (run `midas align` for per-stream jitter and drift, `midas eval sync` for offsets)"


def recorded_statement(manifest: dict[str, Any]) -> dict[str, Any]:
    """What is known when the recording ends: the method, the clock, each stream's clocks."""
    streams = {}
    for name, entry in manifest.get("streams", {}).items():
        device = [c.get("name") for c in entry.get("columns", []) if isinstance(c, dict) and c.get("clock") == "device"]
        streams[name] = {"stamp": "t_host_ns at read", "device_clock": device[0] if device else None,
                         "nominal_rate_hz": entry.get("nominal_rate_hz")}
    rig = manifest.get("rig")
    rig = rig if isinstance(rig, dict) else {}
    method = SIMULATED if rig.get("simulated") else IMPORTED if rig.get("imported") else METHOD
    priority = worker_priority(manifest)  # only recordings have workers (a simulated session's bytes stay)
    return {"method": method, "clock": manifest.get("clock"), "streams": streams,
            **({"worker_priority": priority} if priority else {})}


def worker_priority(manifest: dict[str, Any]) -> dict[str, Any]:
    """Each device worker's scheduling priority as recorded (``record --priority``: asked, got, nice read
    back in the worker); {} for a session recorded before midas kept it, or not recorded live."""
    devices = manifest.get("devices")
    devices = devices if isinstance(devices, dict) else {}
    return {name: {k: entry["priority"].get(k) for k in ("asked", "got", "nice")}
            for name, entry in devices.items() if isinstance(entry, dict) and isinstance(entry.get("priority"), dict)}


def _json_entry(path: Path, key: str) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8")).get(key)
    except (OSError, ValueError, AttributeError):
        return None


def statement(folder: Path | str, manifest: dict[str, Any]) -> dict[str, Any]:
    """The full statement: ``recorded_statement`` plus each stream's clock fit and the measured offsets
    when `midas align` / `midas eval sync` have run (else says they were not measured)."""
    folder = Path(folder)
    document = recorded_statement(manifest)
    fits = _json_entry(folder / "derived" / "aligned.json", "clock_fit")
    for name, entry in document["streams"].items():
        fit = fits.get(name) if isinstance(fits, dict) else None
        entry["fit"] = fit if isinstance(fit, dict) else NOT_MEASURED
        if isinstance(fit, dict) and isinstance(fit.get("clock"), str):
            entry["device_clock"] = fit["clock"]  # what the fit used: a declared column no row filled gave way
    rows = _json_entry(folder / "derived" / "eval" / "sync.json", "rows")
    offsets: Any = rows.get("sync") if isinstance(rows, dict) else None
    document["measured_offsets"] = [{k: r.get(k) for k in ("pair", "evidence", "offset_ms", "spread_ms", "drift_ppm",
                                                            "verdict")} for r in offsets if isinstance(r, dict)] \
        if isinstance(offsets, list) else NOT_MEASURED
    return document
