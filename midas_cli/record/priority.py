"""The device workers' scheduling priority (`midas record --priority normal|high`, ``[record] priority``).

On a busy host the error of ``t_host_ns`` is mostly the device worker waiting for a CPU (BENCHMARKS.md
section 10). ``high`` lowers each worker's nice value to ``HIGH_NICE`` right after it starts, before it
opens its device or starts a thread (threads inherit it; on Linux a nice value belongs to a thread). Only
the workers: the recorder, its fork server and the resource tracker keep theirs.

Nice, not SCHED_FIFO/SCHED_RR: a real-time worker that spins (a device flooding it, a bug) would starve
everything else on a 2-core host, the recorder and the terminal included, while a nice worker only gets
a larger share. nice -10 is what the benchmark measured; it needs root, CAP_SYS_NICE or RLIMIT_NICE >= 30.

Without permission the worker records at the priority it has and says so; what each worker got is read
back with ``os.getpriority``, never assumed from the request, and goes into the manifest
(``devices.<name>.priority``) and the sync statement.
"""

from __future__ import annotations

import os
import resource
from pathlib import Path
from typing import Any

from midas_cli.config import PRIORITY_CHOICES
from midas_cli.errors import ConfigError

HIGH_NICE = -10
CAP_SYS_NICE = 23  # bit of the capability in /proc/self/status CapEff
HOW_TO_ALLOW = ("allow nice -10 for this user: `ulimit -e 30` in a root shell before starting midas, or a line "
                "`@GROUP - nice -10` in /etc/security/limits.conf (log in again), or "
                "`sudo setcap cap_sys_nice+ep PYTHON` (the real file of the venv's python)")


def apply_priority(asked: str) -> dict[str, Any]:
    """Set this process's (thread's) priority as ``asked`` ("normal": left as it is; "high": nice
    HIGH_NICE unless already at or below it). Returns what is in force: ``asked``, ``nice`` (read back),
    ``got`` ("high" when nice <= HIGH_NICE, else "normal") and, when the OS refused, ``error``."""
    result: dict[str, Any] = {"asked": asked}
    if asked == "high" and os.getpriority(os.PRIO_PROCESS, 0) > HIGH_NICE:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, HIGH_NICE)
        except OSError as exc:  # PermissionError: EPERM/EACCES (no root, CAP_SYS_NICE or RLIMIT_NICE)
            result["error"] = exc.strerror or type(exc).__name__
    nice = os.getpriority(os.PRIO_PROCESS, 0)
    result.update(nice=nice, got="high" if nice <= HIGH_NICE else "normal")
    return result


def denied_warning(results: dict[str, dict[str, Any]]) -> str | None:
    """One warning line when ``high`` was asked and some workers (by device) did not get it, else None."""
    denied = sorted(name for name, r in results.items() if r.get("asked") == "high" and r.get("got") != "high")
    if not denied:
        return None
    reason = next((results[name]["error"] for name in denied if results[name].get("error")), "not permitted")
    return (f"midas: warning: --priority high: {reason}; {', '.join(denied)} record at normal priority "
            f"(nice {HIGH_NICE} needs root, CAP_SYS_NICE or RLIMIT_NICE >= {20 - HIGH_NICE}); to {HOW_TO_ALLOW}")


def high_permitted(status_file: Path = Path("/proc/self/status")) -> dict[str, Any]:
    """Whether this user may set nice HIGH_NICE (cheap: no priority is changed), and why: ``permitted``,
    ``by`` ("root", "CAP_SYS_NICE", "RLIMIT_NICE" or None) and ``how`` (to allow it, when not)."""
    by = None
    if os.geteuid() == 0:
        by = "root"
    elif _has_cap_sys_nice(status_file):
        by = "CAP_SYS_NICE"
    else:
        soft = resource.getrlimit(resource.RLIMIT_NICE)[0]
        if soft == resource.RLIM_INFINITY or 20 - soft <= HIGH_NICE:
            by = "RLIMIT_NICE"
    return {"permitted": by is not None, "by": by, "how": "" if by else HOW_TO_ALLOW}


def _has_cap_sys_nice(status_file: Path) -> bool:
    """CAP_SYS_NICE in this process's effective capabilities (False when they cannot be read)."""
    try:
        for line in status_file.read_text(encoding="ascii", errors="replace").splitlines():
            if line.startswith("CapEff:"):
                return bool(int(line.split()[1], 16) >> CAP_SYS_NICE & 1)
    except (OSError, ValueError, IndexError):
        return False
    return False


def checked_priority(value: str, source: str) -> str:
    """``value`` when it is one of PRIORITY_CHOICES; else ConfigError naming ``source`` (e.g. --priority)."""
    if value not in PRIORITY_CHOICES:
        raise ConfigError(f"{source} must be one of {', '.join(PRIORITY_CHOICES)}, got {value!r}")
    return value
