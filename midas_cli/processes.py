"""Is a process still there? One answer for every place that asks (the recorder's workers, the control
socket, run folders, OBS's saved settings).

A zombie (ended, not yet reaped: common in containers whose PID 1 reaps nobody) holds its PID and
start time until its parent reaps it; it counts as gone. Where there is no /proc (macOS) the PID alone
decides.
"""

from __future__ import annotations

import os
from pathlib import Path


def process_start(pid: int) -> str | None:
    """When process ``pid`` started (clock ticks since boot, from /proc), None if there is no such
    process or it has ended (a zombie); "" where /proc cannot tell (the PID alone then decides)."""
    if pid <= 0:
        return None
    if not Path("/proc/self/stat").exists():  # no procfs (macOS)
        return _pid_exists_without_proc(pid)
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return None
    except OSError:
        return _pid_exists_without_proc(pid)
    fields = text[text.rindex(")") + 2 :].split()  # from field 3 of proc(5), counted after "pid (comm)"
    if fields[0] in ("Z", "X"):  # ended: a zombie holds its PID and start time until its parent reaps it
        return None
    return fields[19]  # field 22: start time


def process_alive(pid: int) -> bool:
    """True while process ``pid`` runs (a zombie is gone; someone else's process is alive)."""
    return process_start(pid) is not None


def _pid_exists_without_proc(pid: int) -> str | None:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return None
    except PermissionError:  # exists, owned by another user
        return ""
    return ""
