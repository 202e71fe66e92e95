"""What every benchmark records about the machine it ran on, and where results go."""

from __future__ import annotations

import json
import os
import platform
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

RESULTS = Path(os.environ.get("MIDAS_BENCH_RESULTS", Path(__file__).resolve().parent / "results"))


def load_average() -> float:
    """1-minute load average now (the machine may be shared: compare figures at similar load)."""
    return round(os.getloadavg()[0], 2)


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def memory_gib() -> float | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass
    return None


def machine_info() -> dict[str, Any]:
    return {"cpus": os.cpu_count(), "affinity_cpus": len(os.sched_getaffinity(0)), "cpu_model": cpu_model(),
            "memory_gib": memory_gib(), "platform": platform.platform(), "python": platform.python_version(),
            "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds")}


def write_result(name: str, report: dict[str, Any]) -> Path:
    """Write ``results/<name>.json`` and echo it on stdout."""
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    print(json.dumps(report, indent=2))
    return path
