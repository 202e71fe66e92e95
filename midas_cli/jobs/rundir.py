"""The run folder of a batch run: what to do (``plan.json``) and how far it got (one marker per unit).

``RUN_DIR/``
  ``plan.json``                 ``{"task", "created", "units": [{"index", "name", "args", "fingerprint"}]}``;
                                rewritten by each submission with the inputs' current fingerprints
  ``submissions.json``          every submission: executor, SLURM job id, the units it ran, when
  ``units/<k>/running.json``    host, pid, SLURM job/task id, start time (written when unit k starts)
  ``units/<k>/done.json``       fingerprint, result (what the command renders), output files, seconds
  ``units/<k>/failed.json``     fingerprint, the last error line, the log file
  ``logs/unit-<k>.log``         the unit's log (a SLURM task's stdout and stderr)

A unit is *done* when its ``done.json`` carries the plan's fingerprint for it and every output file it
lists still exists; *stale* when its inputs or options changed since (a different fingerprint) or an
output is gone: it runs again. Every file is written atomically (temporary + rename), so a reader on
another node never sees half a marker.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable, Literal, overload

from midas_cli.errors import ConfigError, SessionError

PLAN = "plan.json"
SUBMISSIONS = "submissions.json"
MARKERS = ("running", "done", "failed")
_SLURM_IDS = {"job_id": (str,), "task_id": (str,), "step_job_id": (str,)}
# what a marker's keys must hold when present (a run folder is data: it may have been edited or damaged)
MARKER_TYPES: dict[str, dict[str, tuple[type, ...]]] = {
    "running": {"unit": (int,), "name": (str,), "host": (str,), "pid": (int,), "started": (str,), **_SLURM_IDS},
    "done": {"unit": (int,), "name": (str,), "fingerprint": (str,), "finished": (str,), "seconds": (float, int),
             "host": (str,), "outputs": (list,), **_SLURM_IDS},
    "failed": {"unit": (int,), "name": (str,), "fingerprint": (str,), "finished": (str,), "error": (str,),
               "log": (str,), "exit_code": (int,), "host": (str,), **_SLURM_IDS},
}
UNIT_TYPES: dict[str, tuple[type, ...]] = {"index": (int,), "name": (str,), "args": (dict,), "fingerprint": (str,)}
SUBMISSION_TYPES: dict[str, tuple[type, ...]] = {"executor": (str,), "job_id": (str,), "units": (list,),
                                                 "script": (str,), "submitted": (str,), "jobs": (int,)}


@dataclass(frozen=True)
class Unit:
    """One independent piece of work: ``args`` (JSON) go to the task's function; ``fingerprint`` names
    its inputs and options (a different one makes an earlier result stale)."""

    name: str
    args: dict[str, Any]
    fingerprint: str
    index: int = 0


@dataclass
class Plan:
    task: str
    units: list[Unit]
    created: str = field(default_factory=lambda: now_utc())


def now_utc() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def fingerprint(*parts: Any) -> str:
    """sha256 (hex, 16 chars) of ``parts`` as canonical JSON (paths and other objects as str)."""
    text = json.dumps(parts, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


def file_digest(path: Path) -> str:
    """sha256 of a file's bytes ('' for a missing file); SessionError when it cannot be read (a folder, or
    a file where a folder above it should be)."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
    except FileNotFoundError:
        return ""
    except OSError as exc:
        raise SessionError(f"cannot read {path}: {exc.strerror or exc} (a file where a folder should be, or the "
                           "other way round?)") from None
    return digest.hexdigest()


def write_json(path: Path, data: Any) -> None:
    """``data`` as JSON at ``path``, atomically (a unique temporary renamed into place)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=2, default=str)
            f.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


_JSON_NAMES = {int: "an integer", float: "a number", str: "a string", dict: "an object", list: "a list"}


def type_problem(data: dict[str, Any], types: dict[str, tuple[type, ...]]) -> str | None:
    """The first key of ``data`` whose value has the wrong type, said as ``key = value should be a T``
    (None: all fit; a key may be missing; a bool is not an int; lists hold str, or int for ``units``)."""
    for key, accepted in types.items():
        if key not in data:
            continue
        value = data[key]
        item = int if key == "units" else str
        ok = isinstance(value, accepted) and not isinstance(value, bool)
        if ok and isinstance(value, list):
            ok = all(isinstance(v, item) and not isinstance(v, bool) for v in value)
        if not ok:
            expected = (f"a list of {'integers' if item is int else 'strings'}" if list in accepted
                        else _JSON_NAMES[accepted[0]])
            return f"{key} = {json.dumps(value, default=str)[:60]} should be {expected}"
    return None


def read_json(path: Path) -> Any | None:
    """The JSON at ``path``; None when it is missing or unreadable (a marker being replaced)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


class RunDir:
    """A run folder (created on demand)."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path).expanduser().resolve()

    def unit_dir(self, index: int) -> Path:
        return self.path / "units" / str(index)

    def marker(self, index: int, kind: str) -> Path:
        return self.unit_dir(index) / f"{kind}.json"

    def log(self, index: int) -> Path:
        return self.path / "logs" / f"unit-{index}.log"

    def write_plan(self, plan: Plan) -> Plan:
        """Save ``plan`` (its units numbered 0..n-1 in order); a run folder of another task is refused."""
        old = self.read_plan(missing_ok=True)
        if old is not None and old.task != plan.task:
            raise ConfigError(f"run folder {self.path} belongs to a '{old.task}' run, not '{plan.task}': "
                              "give another --run-dir")
        units = [Unit(u.name, u.args, u.fingerprint, i) for i, u in enumerate(plan.units)]
        plan = Plan(plan.task, units, plan.created)
        try:
            (self.path / "logs").mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"cannot create run folder {self.path}: {exc.strerror or exc}") from exc
        write_json(self.path / PLAN, {"task": plan.task, "created": plan.created,
                                      "units": [{"index": u.index, "name": u.name, "args": u.args,
                                                 "fingerprint": u.fingerprint} for u in units]})
        return plan

    @overload
    def read_plan(self, missing_ok: Literal[False] = False) -> Plan: ...

    @overload
    def read_plan(self, missing_ok: bool) -> Plan | None: ...

    def read_plan(self, missing_ok: bool = False) -> Plan | None:
        """The plan; ConfigError when there is none (not a run folder), SessionError when it is malformed."""
        data: Any = read_json(self.path / PLAN)  # None: missing, unreadable or not JSON
        if data is None and not (self.path / PLAN).exists():
            if missing_ok:
                return None
            raise ConfigError(f"{self.path} is not a midas run folder (no {PLAN})")
        problem = _plan_problem(data)
        if problem:
            raise SessionError(f"{self.path / PLAN} is malformed ({problem}); remove the run folder and run again")
        units = [Unit(u["name"], u["args"], u["fingerprint"], u["index"]) for u in data["units"]]
        return Plan(data["task"], units, data.get("created", ""))

    def read_marker(self, index: int, kind: str) -> dict[str, Any] | None:
        """Unit ``index``'s ``kind`` marker (None: none, or unreadable); SessionError naming the file and key
        when a value has the wrong type."""
        data = read_json(self.marker(index, kind))
        if not isinstance(data, dict):
            return None
        problem = type_problem(data, MARKER_TYPES[kind])
        if problem:
            raise SessionError(f"{self.marker(index, kind)}: {problem}; delete the file (the unit runs again)")
        return data

    def write_marker(self, index: int, kind: str, data: dict[str, Any]) -> None:
        write_json(self.marker(index, kind), data)

    def clear(self, index: int, kinds: Iterable[str] = MARKERS) -> None:
        for kind in kinds:
            self.marker(index, kind).unlink(missing_ok=True)

    def is_done(self, unit: Unit) -> bool:
        """Finished with the same inputs (fingerprint) and every output it lists still there."""
        done = self.read_marker(unit.index, "done")
        return bool(done and done.get("fingerprint") == unit.fingerprint
                    and all(Path(p).exists() for p in done.get("outputs", [])))

    def submissions(self) -> list[dict[str, Any]]:
        """Every submission so far ([] when none); SessionError naming the entry and key when one is malformed."""
        data = read_json(self.path / SUBMISSIONS)
        if not isinstance(data, list):
            return []
        for n, entry in enumerate(data):
            problem = "not an object" if not isinstance(entry, dict) else type_problem(entry, SUBMISSION_TYPES)
            if problem:
                raise SessionError(f"{self.path / SUBMISSIONS}: entry {n}: {problem}; remove the run folder and "
                                   "run again")
        return data

    def add_submission(self, entry: dict[str, Any]) -> None:
        write_json(self.path / SUBMISSIONS, [*self.submissions(), entry])


def _plan_problem(data: Any) -> str | None:
    """What is wrong with plan.json's content (None: a task name and one or more units numbered 0..n-1 in
    order)."""
    if not isinstance(data, dict) or not isinstance(data.get("task"), str) or not isinstance(data.get("units"), list):
        return "expected {\"task\": name, \"units\": [...]}"
    if not isinstance(data.get("created", ""), str):
        return "created should be a str"
    if not data["units"]:
        return "no units: midas never plans an empty run"
    for k, unit in enumerate(data["units"]):
        if not isinstance(unit, dict):
            return f"unit {k} is not an object"
        missing = next((key for key in UNIT_TYPES if key not in unit), None)
        problem = f"no {missing}" if missing else type_problem(unit, UNIT_TYPES)
        if problem:
            return f"unit {k}: {problem}"
        if unit["index"] != k:
            return f"unit {k} says index {unit['index']}"
    return None


def log_error_line(path: Path, max_bytes: int = 65536) -> str:
    """The last line of a log that looks like an error (else its last line)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - max_bytes))
            text = f.read().decode("utf-8", errors="replace")
    except OSError:
        return ""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    for line in reversed(lines):
        lower = line.lower()
        if "error" in lower or "killed" in lower or "cancelled" in lower or "exception" in lower:
            return line
    return lines[-1] if lines else ""
