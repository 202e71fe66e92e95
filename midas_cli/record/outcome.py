"""What a finished recording's manifest says went wrong, per stream: the end-of-run summary.

Pure functions of the manifest (no I/O), shared by the final table, the ``--status-json`` final
object and the tests, so every view reports the same counts.
"""

from __future__ import annotations

from typing import Any


def stream_outcomes(manifest: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per stream: samples, measured rate, samples missing in device outages and unexplained,
    dropped and corrupt counts, and the reconnects of the device that produced it."""
    devices = manifest.get("devices") or {}
    outcomes = {}
    for name, entry in (manifest.get("streams") or {}).items():
        gaps = entry.get("seq_gaps") or {}
        explained = entry.get("missing_explained") or {}
        missing = int(gaps.get("missing", 0) or 0)
        outage = min(int(explained.get("outage", 0) or 0), missing)
        skipped = min(int(explained.get("skipped", 0) or 0), missing - outage)  # frames the live recognition skipped
        device = devices.get(entry.get("device"), {})
        outcomes[name] = {
            "samples": entry.get("samples"),
            "measured_rate_hz": entry.get("measured_rate_hz"),
            "nominal_rate_hz": entry.get("nominal_rate_hz"),
            "missing": missing,
            "missing_outage": outage,
            "missing_skipped": skipped,
            "missing_unexplained": missing - outage - skipped,
            "gaps": int(gaps.get("count", 0) or 0),
            "dropped": int(entry.get("dropped", 0) or 0),
            "corrupt": int(entry.get("corrupt", 0) or 0),
            "reconnects": int(device.get("reconnects", 0) or 0),
            "p99_latency_ms": (entry.get("latency_ms") or {}).get("p99"),
        }
    return outcomes


def recording_problems(manifest: dict[str, Any]) -> list[str]:
    """One sentence per stream or device that did not record cleanly (empty: nothing went wrong)."""
    problems = []
    for name, o in stream_outcomes(manifest).items():
        parts = []
        if o["missing_outage"]:
            parts.append(f"{o['missing_outage']} samples missing during device outages")
        if o["missing_skipped"]:
            parts.append(f"{o['missing_skipped']} frames skipped (the recognition was behind)")
        if o["missing_unexplained"]:
            parts.append(f"{o['missing_unexplained']} samples missing without an outage")
        if o["dropped"]:
            parts.append(f"{o['dropped']} rows read but not written")
        if o["corrupt"]:
            parts.append(f"{o['corrupt']} corrupt records discarded")
        if not o["samples"] and o["nominal_rate_hz"] is not None:
            parts.append("no samples at all")
        if parts:
            problems.append(f"{name}: " + ", ".join(parts))
    for device, entry in (manifest.get("devices") or {}).items():
        if entry.get("reconnects"):
            problems.append(f"{device}: reconnected {entry['reconnects']} time(s)")
        check = (entry.get("info") or {}).get("recording") or {}
        if check.get("status") not in (None, "ok"):
            details = "; ".join(check.get("problems") or []) or check["status"]
            problems.append(f"{device}: video file check: {details}")
    return problems
