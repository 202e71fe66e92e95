"""CPU per process of a running `midas record` (from /proc): the recorder, each device worker, the rest.

A worker is named by the stream files it holds open (``streams/<name>.csv``: it appends to them itself);
the recorder is the root process; anything else (the fork server, multiprocessing's resource tracker)
is "other". Linux only (reads /proc).
"""

from __future__ import annotations

import os
from pathlib import Path

TICKS = os.sysconf("SC_CLK_TCK")


def process_tree(pid: int) -> list[int]:
    """``pid`` and all its descendants alive now."""
    found = [pid]
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return found
    for task in tasks:
        try:
            children = Path(f"/proc/{pid}/task/{task}/children").read_text().split()
        except OSError:
            continue
        for child in children:
            found += process_tree(int(child))
    return found


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of ``pid`` so far (None once it is gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat[stat.rfind(")") + 2:].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


def role(pid: int, root: int) -> str:
    if pid == root:
        return "recorder"
    streams = []
    try:
        for fd in os.listdir(f"/proc/{pid}/fd"):
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
            if "/streams/" in target and target.endswith(".csv"):
                streams.append(Path(target).stem)
    except OSError:
        pass
    return "worker " + "+".join(sorted(streams)) if streams else "other"


def snapshot(root: int) -> dict[int, tuple[str, float]]:
    """Every process of the tree now: pid -> (role, CPU seconds)."""
    out = {}
    for pid in process_tree(root):
        seconds = cpu_seconds(pid)
        if seconds is not None:
            out[pid] = (role(pid, root), seconds)
    return out


def percent_between(before: dict[int, tuple[str, float]], after: dict[int, tuple[str, float]],
                    wall_s: float) -> dict[str, float]:
    """Per role, % of one core used between two snapshots ``wall_s`` apart (processes in both), and the total."""
    shares: dict[str, float] = {}
    for pid, (name, seconds) in after.items():
        if pid in before:
            label = before[pid][0] if before[pid][0] != "other" else name
            shares[label] = shares.get(label, 0.0) + 100 * (seconds - before[pid][1]) / wall_s
    result = {k: round(v, 1) for k, v in sorted(shares.items())}
    result["total"] = round(sum(shares.values()), 1)
    return result
