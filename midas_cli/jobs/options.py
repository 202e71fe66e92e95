"""Where a batch command's units run: its executor options as given (``BatchOptions``, what
``--executor``, ``--jobs``, ``--run-dir``, ``--no-wait`` and ``--slurm-*`` said) and, checked, the
``ExecutorChoice`` that ``batch.run_plan`` follows. Light to import: a command's module imports it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

from midas_cli.errors import ConfigError

if TYPE_CHECKING:
    from midas_cli.jobs.slurm import SlurmSettings

EXECUTORS = ("local", "slurm")


@dataclass
class ExecutorChoice:
    """Where units run, checked: ``slurm`` holds the SLURM settings (flags over the config's ``[slurm]``)
    with ``executor == "slurm"``."""

    executor: str = "local"
    jobs: int = 1
    run_dir: Optional[Path] = None
    wait: bool = True
    slurm: Optional[SlurmSettings] = None

    @property
    def in_process(self) -> bool:
        """The units run one after another in this process (so a progress callback can reach them)."""
        return self.executor == "local" and self.jobs == 1


@dataclass(frozen=True)
class BatchOptions:
    """A batch command's executor options as given (``--executor``, ``--jobs``, ``--run-dir``,
    ``--no-wait``, ``--slurm-*``), not yet checked: ``choice()`` checks them."""

    executor: str = "local"
    jobs: int = 1
    run_dir: Optional[Path] = None
    no_wait: bool = False
    slurm_partition: Optional[str] = None
    slurm_time: Optional[str] = None
    slurm_mem: Optional[str] = None
    slurm_gpus: Optional[int] = None
    slurm_array_parallelism: Optional[int] = None

    def choice(self, gpu: bool = False) -> ExecutorChoice:
        """The options checked (one-line ConfigError on a bad one), with slurm the settings too (flags and
        the config's ``[slurm]``, in SLURM's grammar) before any work starts. ``gpu``: every unit needs a
        GPU, so without ``--slurm-gpus`` a SLURM task asks for the config's ``gpus`` or 1."""
        if self.executor not in EXECUTORS:
            raise ConfigError(f"--executor must be {' or '.join(EXECUTORS)}, got {self.executor!r}")
        if self.jobs < 1:
            raise ConfigError(f"--jobs must be >= 1, got {self.jobs}")
        flags = self.slurm_flags()
        if self.executor == "local":
            given = [f"--slurm-{k.replace('_', '-')}" for k, v in flags.items() if v is not None]
            if self.no_wait or given:
                raise ConfigError(f"{(['--no-wait'] if self.no_wait else given)[0]} needs --executor slurm")
            return ExecutorChoice(self.executor, self.jobs, self.run_dir, not self.no_wait)
        if self.jobs != 1:
            raise ConfigError("--jobs is for --executor local; SLURM runs every unit as its own task "
                              "(--slurm-array-parallelism caps how many at once)")
        from midas_cli import config
        from midas_cli.jobs.slurm import SlurmSettings

        section = config.section("slurm")
        if gpu and flags["gpus"] is None:
            flags["gpus"] = section.get("gpus") or 1
        return ExecutorChoice(self.executor, self.jobs, self.run_dir, not self.no_wait,
                              SlurmSettings.merged(flags, section))

    def slurm_flags(self) -> dict[str, Any]:
        """The ``--slurm-*`` values by setting name (None: not given)."""
        return {"partition": self.slurm_partition, "time": self.slurm_time, "mem": self.slurm_mem,
                "gpus": self.slurm_gpus, "array_parallelism": self.slurm_array_parallelism}
