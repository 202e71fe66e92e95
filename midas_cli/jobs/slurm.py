"""The SLURM executor: one ``sbatch --array`` job per submission, one array task per unit to run.

Each array task runs ``<this python> -m midas_cli jobs run-unit RUN_DIR --unit $SLURM_ARRAY_TASK_ID``
(the same code a local run calls), its stdout and stderr in ``RUN_DIR/logs/unit-<k>.log``. The script
is kept as ``RUN_DIR/slurm-<n>.sh`` and the sbatch arguments in ``submissions.json``, so an admin can
read, or resubmit, exactly what ran. Settings reach sbatch only as arguments (checked against SLURM's
grammar), never as text of the script, which holds nothing taken from a flag or a file. The run
folder must be on a file system the compute nodes share (so must the sessions and the Python
environment); the job inherits the submitting shell's environment (sbatch's default ``--export=ALL``).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from dataclasses import asdict, dataclass, fields
from typing import Any, Sequence

from midas_cli.config import slurm_value_problem
from midas_cli.errors import ConfigError
from midas_cli.jobs.rundir import RunDir

SBATCH_TIMEOUT_S = 60.0
FLAGGED = {"partition", "time", "mem", "gpus", "array_parallelism"}  # the settings with a --slurm-* flag
SBATCH_FLAGS = (("partition", "--partition"), ("time", "--time"), ("mem", "--mem"), ("account", "--account"),
                ("qos", "--qos"), ("cpus_per_task", "--cpus-per-task"))
OUTPUT_PATTERN_CHARS = "%\\\n"  # sbatch reads % and \ in --output as a file name pattern


@dataclass(frozen=True)
class SlurmSettings:
    """What every array task asks for (None: the cluster's default). ``gpus`` > 0 adds ``--gres=gpu:N``;
    ``array_parallelism`` caps the tasks running at once (``--array=...%N``). Every value is checked
    against SLURM's grammar (``config.slurm_value_problem``) and reaches sbatch only as an argument."""

    partition: str | None = None
    time: str | None = None
    mem: str | None = None
    gpus: int = 0
    array_parallelism: int | None = None
    account: str | None = None
    qos: str | None = None
    cpus_per_task: int | None = None

    def __post_init__(self) -> None:
        for name in (f.name for f in fields(self)):
            value = getattr(self, name)
            problem = None if value is None else slurm_value_problem(name, value)
            if problem:
                where = f"--slurm-{name.replace('_', '-')}" if name in FLAGGED else f"[slurm] {name}"
                raise ConfigError(f"{where} {value!r} {problem}")

    @classmethod
    def merged(cls, flags: dict[str, Any], config: dict[str, Any]) -> SlurmSettings:
        """The flags given (not None) over the config's ``[slurm]`` section."""
        known = {f.name for f in fields(cls)}
        values = {k: v for k, v in config.items() if k in known}
        values.update({k: v for k, v in flags.items() if v is not None and k in known})
        return cls(**values)

    def sbatch_options(self) -> list[str]:
        """The settings as sbatch arguments (``--partition=gpu``, ...)."""
        options = [f"{flag}={getattr(self, name)}" for name, flag in SBATCH_FLAGS if getattr(self, name) is not None]
        if self.gpus:
            options.append(f"--gres=gpu:{self.gpus}")
        return options


def array_spec(indices: Sequence[int], parallelism: int | None) -> str:
    """``0-3,7,9-10`` (ranges compressed) with ``%N`` when capped."""
    parts: list[str] = []
    ordered = sorted(set(indices))
    start = prev = ordered[0]
    for k in [*ordered[1:], None]:
        if k is not None and k == prev + 1:
            prev = k
            continue
        parts.append(str(start) if start == prev else f"{start}-{prev}")
        if k is not None:
            start = prev = k
    return ",".join(parts) + (f"%{parallelism}" if parallelism else "")


def sbatch_arguments(run_dir: RunDir, task: str, indices: Sequence[int], settings: SlurmSettings) -> list[str]:
    """Everything sbatch is told besides the script, as separate arguments (never as script text)."""
    log = str(run_dir.path / "logs" / "unit-%a.log")
    if any(c in str(run_dir.path) for c in OUTPUT_PATTERN_CHARS):
        raise ConfigError(f"run folder {str(run_dir.path)!r}: sbatch reads '%' and '\\' in a log path as a pattern "
                          "(and a line break cannot be one); choose another --run-dir")
    return [f"--job-name=midas-{task}", f"--array={array_spec(indices, settings.array_parallelism)}",
            f"--output={log}", *settings.sbatch_options()]


def script() -> str:
    """The batch script of every submission: it only runs the array task's unit (the run folder is its
    first argument; the sbatch options are arguments of sbatch, listed in ``submissions.json``)."""
    command = [sys.executable, "-m", "midas_cli", "jobs", "run-unit"]
    lines = ["#!/bin/bash",
             "# one unit of a midas run folder per array task (midas jobs status RUN_DIR shows them);",
             "# usage: sbatch [options] slurm-N.sh RUN_DIR (the options of each submission: submissions.json)",
             "# numpy, torch and OpenCV threads: the CPUs SLURM gave the task, not the whole node's",
             'export OMP_NUM_THREADS="${OMP_NUM_THREADS:-${SLURM_CPUS_PER_TASK:-1}}"',
             f'exec {shlex.join(command)} "$1" --unit "$SLURM_ARRAY_TASK_ID"']
    return "\n".join(lines) + "\n"


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        raise ConfigError(f"--executor slurm needs SLURM's {name} on PATH (run on a cluster login node, or use "
                          "--executor local)")
    return path


def max_array_size() -> int | None:
    """The cluster's MaxArraySize (array task ids must stay below it; SLURM's default is 1001), or None
    when ``scontrol`` cannot say."""
    scontrol = shutil.which("scontrol")
    if scontrol is None:
        return None
    try:
        result = subprocess.run([scontrol, "show", "config"], capture_output=True, text=True, timeout=SBATCH_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return None
    match = re.search(r"^MaxArraySize\s*=\s*(\d+)", result.stdout, re.MULTILINE)
    return int(match[1]) if match else None


def submit(run_dir: RunDir, task: str, indices: Sequence[int], settings: SlurmSettings) -> dict[str, Any]:
    """Write the script and sbatch it; the submission record (job id, units, script)."""
    limit = max_array_size()
    if limit is not None and max(indices) >= limit:
        raise ConfigError(f"this run has {max(indices) + 1} units but the cluster's MaxArraySize is {limit} (array "
                          f"task ids 0..{limit - 1}): run the inputs in batches of at most {limit}, each with its own "
                          "--run-dir, or ask the cluster's admin to raise MaxArraySize")
    number = len(run_dir.submissions())
    path = run_dir.path / f"slurm-{number}.sh"
    arguments = [*sbatch_arguments(run_dir, task, indices, settings), str(path), str(run_dir.path)]
    path.write_text(script(), encoding="utf-8")
    for k in indices:  # a task's log starts empty (sbatch appends to nothing, a local run's log goes)
        run_dir.log(k).unlink(missing_ok=True)
    try:
        result = subprocess.run([_tool("sbatch"), "--parsable", *arguments], capture_output=True, text=True,
                                timeout=SBATCH_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise ConfigError(f"sbatch did not answer within {SBATCH_TIMEOUT_S:.0f} s (is slurmctld up?)") from None
    if result.returncode != 0:
        raise ConfigError(f"sbatch refused {path}: {result.stderr.strip() or result.stdout.strip()}")
    job_id = result.stdout.strip().split(";")[0]
    return {"executor": "slurm", "job_id": job_id, "units": list(indices), "script": str(path),
            "settings": asdict(settings), "sbatch": arguments}


def queued(job_id: str) -> dict[int, str] | None:
    """Array task -> SLURM state (PENDING, RUNNING, ...) of the tasks of ``job_id`` still in the queue;
    None when squeue cannot be asked (then nothing is concluded from the queue)."""
    squeue = shutil.which("squeue")
    if squeue is None:
        return None
    try:
        result = subprocess.run([squeue, "-h", "-r", "-j", job_id, "-o", "%K %T"], capture_output=True, text=True,
                                timeout=SBATCH_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return None
    if result.returncode != 0:
        # a job that left the queue long ago: "Invalid job id specified"; anything else: unknown
        return {} if "invalid job id" in result.stderr.lower() else None
    tasks: dict[int, str] = {}
    for line in result.stdout.splitlines():
        task, _, state = line.strip().partition(" ")
        if task.isdigit():
            tasks[int(task)] = state
        elif "[" in task:  # pending tasks not yet split off: 3-7%2 or 1,4
            for part in task.strip("[]").split("%")[0].split(","):
                low, _, high = part.partition("-")
                if low.isdigit():
                    tasks.update({k: state for k in range(int(low), int(high or low) + 1)})
    return tasks


def cancel(job_id: str) -> None:
    scancel = shutil.which("scancel")
    if scancel:
        subprocess.run([scancel, job_id], capture_output=True, timeout=SBATCH_TIMEOUT_S)


def is_slurm_task() -> bool:
    """This process is itself a SLURM array task (its output already goes to the unit's log)."""
    return bool(os.environ.get("SLURM_ARRAY_TASK_ID"))


def in_use(run_dir: RunDir) -> str | None:
    """The id of a SLURM job of ``run_dir`` still in the queue, if any."""
    for entry in reversed(run_dir.submissions()):
        if entry.get("executor") == "slurm" and entry.get("job_id"):
            tasks = queued(str(entry["job_id"]))
            if tasks:
                return str(entry["job_id"])
    return None
