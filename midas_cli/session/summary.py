"""Readable facts about a session, from its manifest (fast enough for hundreds of folders) and, asked
for, the clock fits `midas align` found (derived/aligned.json)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from midas_cli.session.reader import Session
from midas_cli.session.sync_statement import statement, worker_priority


def summarize_session(session: Session, clock_fits: bool = False) -> dict[str, Any]:
    """Metadata, status, duration and per-stream figures (rates, counts, gaps, drops, latency; with
    ``clock_fits``, each stream's fit of host stamps against its device clock, None before align)."""
    manifest = session.manifest
    streams = {}
    start_ns = manifest["start"].get("host_ns")
    fits = _clock_fits(session.path) if clock_fits else {}
    for name, entry in manifest["streams"].items():
        gaps = entry.get("seq_gaps") or {}
        streams[name] = {
            "device": entry.get("device"),
            "file": entry.get("file"),
            "columns": len(entry.get("columns", [])),
            "nominal_rate_hz": entry.get("nominal_rate_hz"),
            "measured_rate_hz": entry.get("measured_rate_hz"),
            "samples": entry.get("samples"),
            "gaps": gaps.get("count"),
            "missing": gaps.get("missing"),
            "dropped": entry.get("dropped"),
            "corrupt": entry.get("corrupt"),
            "latency_p99_ms": (entry.get("latency_ms") or {}).get("p99"),
            "first_t_host_ns": entry.get("first_t_host_ns"),
            "last_t_host_ns": entry.get("last_t_host_ns"),
            "first_s": _since(entry.get("first_t_host_ns"), start_ns),
            "last_s": _since(entry.get("last_t_host_ns"), start_ns),
            "clock_fit": fits.get(name) if isinstance(fits.get(name), dict) else None,
        }
    devices = {
        name: {"kind": d.get("kind"), "url": d.get("url"), "reconnects": d.get("reconnects"),
               "serial": (d.get("info") or {}).get("serial"), "priority": worker_priority(manifest).get(name)}
        for name, d in manifest["devices"].items()
    }
    return {
        "path": str(session.path),
        "session_id": manifest["session_id"],
        "status": manifest["status"],
        "stop_reason": manifest.get("stop_reason"),
        **{k: manifest["metadata"].get(k) for k in ("task", "subject", "trial", "platform", "operator_note")},
        "start_utc": manifest["start"].get("utc"),
        "duration_s": session.duration_s(),
        "devices": devices,
        "streams": streams,
        **({"sync": statement(session.path, manifest)} if clock_fits else {}),
    }


def _clock_fits(folder: Path) -> dict[str, Any]:
    """Each stream's clock fit (drift, jitter) as ``midas align`` last found it (derived/aligned.json);
    {} when align has not run or the file is unreadable (this is a summary, not a check)."""
    try:
        fits = json.loads((folder / "derived" / "aligned.json").read_text(encoding="utf-8")).get("clock_fit")
    except (OSError, ValueError, AttributeError):
        return {}
    return fits if isinstance(fits, dict) else {}


def _since(t_ns: Any, start_ns: Any) -> float | None:
    """Seconds from the session start (the host clock both are on), or None when either is unknown."""
    if not isinstance(t_ns, int) or not isinstance(start_ns, int):
        return None
    return round((t_ns - start_ns) / 1e9, 6)
