"""Run one unit of a run folder: the same code on this machine and in a SLURM array task."""

from __future__ import annotations

import logging
import os
import socket
import time
import traceback
from typing import Any, Callable

from midas_cli.errors import ConfigError, MidasError, SessionError, disk_full, disk_full_message
from midas_cli.jobs.rundir import RunDir, Unit, now_utc

log = logging.getLogger(__name__)

TaskFn = Callable[..., dict[str, Any]]  # (args, **extra) -> {"result": JSON, "outputs": [paths]}


def slurm_ids() -> dict[str, str]:
    """The SLURM job / array task this process runs in ({} outside SLURM)."""
    names = {"job_id": "SLURM_ARRAY_JOB_ID", "task_id": "SLURM_ARRAY_TASK_ID", "step_job_id": "SLURM_JOB_ID"}
    return {key: os.environ[env] for key, env in names.items() if os.environ.get(env)}


def unit_of(run_dir: RunDir, index: int) -> Unit:
    plan = run_dir.read_plan()
    if not 0 <= index < len(plan.units):
        raise ConfigError(f"--unit {index} is out of range for {run_dir.path} (0..{len(plan.units) - 1})")
    return plan.units[index]


def run_unit(run_dir: RunDir, index: int, fn: TaskFn, log_to_file: bool = True, force: bool = False,
             **extra: Any) -> dict[str, Any]:
    """Run unit ``index`` of ``run_dir`` through ``fn`` (unless it is done with the same fingerprint and
    not ``force``) and mark it done or failed. ``log_to_file``: copy this process's log records to
    ``logs/unit-<k>.log`` (a SLURM task's whole output goes there already). Returns the done marker;
    an error is marked failed and re-raised."""
    unit = unit_of(run_dir, index)
    if not force and run_dir.is_done(unit):
        log.info("%s unit %d (%s): done already, skipped", run_dir.path, index, unit.name)
        return run_dir.read_marker(index, "done") or {}
    run_dir.clear(index)
    run_dir.write_marker(index, "running", {"unit": index, "name": unit.name, "host": socket.gethostname(),
                                            "pid": os.getpid(), "started": now_utc(), **slurm_ids()})
    handler, root_level = None, logging.getLogger().level
    if log_to_file:
        handler = logging.FileHandler(run_dir.log(index), encoding="utf-8")
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        logging.getLogger().addHandler(handler)
        logging.getLogger().setLevel(min(root_level or logging.INFO, logging.INFO))
    started = time.monotonic()
    try:
        log.info("unit %d (%s) starts on %s", index, unit.name, socket.gethostname())
        produced = fn(unit.args, **extra)
        done = {"unit": index, "name": unit.name, "fingerprint": unit.fingerprint, "finished": now_utc(),
                "seconds": round(time.monotonic() - started, 3), "host": socket.gethostname(),
                "result": produced.get("result"), "outputs": [str(p) for p in produced.get("outputs", [])],
                **slurm_ids()}
        run_dir.write_marker(index, "done", done)
        log.info("unit %d (%s) done in %.1f s", index, unit.name, done["seconds"])
        return done
    except Exception as exc:  # Ctrl-C or a SLURM signal leaves no marker: the status says it ended
        full = disk_full(exc)
        if full is not None:  # as the CLI says it for a single run: not a bug, no room
            message, code = disk_full_message(full), SessionError.exit_code
        else:
            message = str(exc) if isinstance(exc, MidasError) else f"{type(exc).__name__}: {exc}"
            code = getattr(exc, "exit_code", 1)
        line = next((x.strip() for x in message.splitlines() if x.strip()), type(exc).__name__)  # its headline
        # INFO: into the unit's log (and onto stderr with --debug); the command reports the failure itself
        if not isinstance(exc, MidasError):
            log.info("unit %d (%s) failed:\n%s", index, unit.name, traceback.format_exc())
        log.info("unit %d (%s) failed: %s", index, unit.name, line)
        run_dir.write_marker(index, "failed", {"unit": index, "name": unit.name, "fingerprint": unit.fingerprint,
                                               "finished": now_utc(), "error": line, "log": str(run_dir.log(index)),
                                               "exit_code": code,
                                               "host": socket.gethostname(), **slurm_ids()})
        raise
    finally:
        run_dir.clear(index, ("running",))
        if handler is not None:
            logging.getLogger().removeHandler(handler)
            logging.getLogger().setLevel(root_level)
            handler.close()
