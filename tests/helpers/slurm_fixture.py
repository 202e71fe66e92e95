"""A real one-node SLURM cluster for the tests: munged, slurmctld and slurmd of Debian's slurm-wlm, run
from a temporary folder (config, munge key, state, spool, logs), on free loopback ports, stopped after.

This host is controller and only compute node (``CPUs`` = nproc). No cgroups, no accounting:
``proctrack/linuxproc``, ``task/none``, ``select/cons_tres`` with ``CR_CPU``. The daemons run as the
test's user (``SlurmUser`` = that user; root in CI). Tests that use the ``slurm`` fixture skip, with
the reason, where the binaries are missing or the daemons do not come up, and fail instead when
``MIDAS_REQUIRE_SLURM=1`` (set by .ci/run, which installs slurm-wlm and munge).
"""

from __future__ import annotations

import getpass
import os
import shutil
import signal
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import pytest

from helpers.net import free_port

REQUIRE_ENV = "MIDAS_REQUIRE_SLURM"
BINARIES = ("munged", "slurmctld", "slurmd", "sbatch", "squeue", "sinfo", "scancel")
SBIN = ("/usr/sbin", "/sbin", "/usr/local/sbin")
START_DEADLINE_S = 60.0


@dataclass
class SlurmCluster:
    root: Path
    conf: Path
    env: dict[str, str]  # SLURM_CONF (and PATH) for every client: sbatch, squeue, midas

    def log_tail(self, lines: int = 30) -> str:
        parts = []
        for name in ("slurmctld.log", "slurmd.log", "munged.log"):
            path = self.root / "log" / name
            text = path.read_text(errors="replace").splitlines()[-lines:] if path.is_file() else ["(none)"]
            parts.append(f"--- {name}\n" + "\n".join(text))
        return "\n".join(parts)


def _which(name: str) -> str | None:
    return shutil.which(name) or shutil.which(name, path=os.pathsep.join(SBIN))


def _unavailable(reason: str) -> None:
    if os.environ.get(REQUIRE_ENV) == "1":
        pytest.fail(f"SLURM is required here ({REQUIRE_ENV}=1) but {reason}", pytrace=False)
    pytest.skip(f"no SLURM test cluster: {reason} (install Debian's slurm-wlm and munge; .ci/run does)")


def _memory_mb() -> int:
    with open("/proc/meminfo", encoding="ascii") as f:
        for line in f:
            if line.startswith("MemTotal:"):
                return max(256, int(line.split()[1]) // 1024 - 512)
    return 1024


def write_config(root: Path, node: str, cpus: int, user: str) -> Path:
    for sub in ("state", "spool", "log", "run", "munge"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    conf = root / "slurm.conf"
    conf.write_text(f"""\
ClusterName=midastest
SlurmctldHost={node}(127.0.0.1)
SlurmUser={user}
SlurmdUser=root
SlurmctldPort={free_port()}
SlurmdPort={free_port()}
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={root / 'munge' / 'munge.sock'}
StateSaveLocation={root / 'state'}
SlurmdSpoolDir={root / 'spool'}
SlurmctldPidFile={root / 'run' / 'slurmctld.pid'}
SlurmdPidFile={root / 'run' / 'slurmd.pid'}
SlurmctldLogFile={root / 'log' / 'slurmctld.log'}
SlurmdLogFile={root / 'log' / 'slurmd.log'}
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
SchedulerType=sched/builtin
MpiDefault=none
ReturnToService=2
SlurmctldTimeout=30
SlurmdTimeout=30
MinJobAge=300
MessageTimeout=20
NodeName={node} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory={_memory_mb()} State=UNKNOWN
PartitionName=debug Nodes={node} Default=YES MaxTime=INFINITE State=UP
""", encoding="ascii")
    return conf


def _die_with_parent() -> None:
    """In the daemon, before exec: SIGTERM it when the process that started it dies (a test run or a
    benchmark killed with SIGKILL would otherwise leave munged, slurmctld and slurmd running)."""
    import ctypes

    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def _start_munge(root: Path, munged: str) -> subprocess.Popen:
    key = root / "munge" / "munge.key"
    key.write_bytes(os.urandom(1024))
    key.chmod(0o400)
    (root / "munge").chmod(0o700)
    return subprocess.Popen([munged, "--foreground", "--force", f"--key-file={key}",
                             f"--socket={root / 'munge' / 'munge.sock'}", f"--pid-file={root / 'run' / 'munged.pid'}",
                             f"--log-file={root / 'log' / 'munged.log'}", f"--seed-file={root / 'munge' / 'seed'}"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, start_new_session=True,
                            preexec_fn=_die_with_parent)


def _node_idle(env: dict[str, str]) -> bool:
    result = subprocess.run(["sinfo", "-h", "-o", "%T"], capture_output=True, text=True, env=env, timeout=30)
    return result.returncode == 0 and result.stdout.strip().rstrip("*") in ("idle", "mixed", "allocated")


def _drain(env: dict[str, str], deadline_s: float = 60.0) -> None:
    """Wait for the queue to empty (a finished task's step daemon reports to slurmctld before it goes:
    stopping the controller first leaves it retrying), cancelling what is left at the deadline."""
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        result = subprocess.run(["squeue", "-h", "-o", "%i"], capture_output=True, text=True, env=env, timeout=30)
        if result.returncode != 0 or not result.stdout.strip():
            return
        time.sleep(0.5)
    subprocess.run(["scancel", "--full", "--user", getpass.getuser()], capture_output=True, env=env, timeout=30)
    time.sleep(2)


def _step_daemons(root: Path) -> list[int]:
    """slurmstepd processes of this cluster (each holds slurmd's log, in ``root``, open)."""
    log = str(root / "log" / "slurmd.log")
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            if "slurmstepd" not in (proc / "cmdline").read_bytes().decode(errors="replace"):
                continue
            if any(os.readlink(fd).startswith(log) for fd in (proc / "fd").iterdir()):
                found.append(int(proc.name))
        except OSError:
            continue
    return found


def _stop(processes: list[subprocess.Popen], root: Path) -> None:
    for process in reversed(processes):
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGTERM)
    for process in reversed(processes):
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait(timeout=10)
    for pid in _step_daemons(root):  # one stuck without its controller: nothing else would end it
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def start_cluster(root: Path) -> Iterator[SlurmCluster]:
    """Start the three daemons in ``root``; yields the cluster, stops every daemon it started."""
    found = {name: _which(name) for name in BINARIES}
    missing = [name for name, path in found.items() if path is None]
    if missing:
        _unavailable(f"{', '.join(missing)} not found")
    node = socket.gethostname().split(".")[0]
    user = getpass.getuser()
    if user != "root":
        _unavailable("slurmd must run as root to start jobs (this test runs as "
                     f"{user})")
    conf = write_config(root, node, len(os.sched_getaffinity(0)), user)  # nproc: never more than the node has
    env = {**os.environ, "SLURM_CONF": str(conf)}
    for name in ("SLURM_JOB_ID", "SLURM_ARRAY_JOB_ID", "SLURM_ARRAY_TASK_ID"):  # a test run inside a SLURM job
        env.pop(name, None)
    processes: list[subprocess.Popen] = []
    try:
        processes.append(_start_munge(root, found["munged"]))
        deadline = time.monotonic() + START_DEADLINE_S
        while not (root / "munge" / "munge.sock").exists():
            if processes[0].poll() is not None or time.monotonic() > deadline:
                _unavailable("munged did not start:\n" + SlurmCluster(root, conf, env).log_tail())
            time.sleep(0.1)
        for daemon in ("slurmctld", "slurmd"):
            args = [found[daemon], "-D", "-f", str(conf)] + (["-i"] if daemon == "slurmctld" else [])
            log = open(root / "log" / f"{daemon}.stderr", "wb")
            processes.append(subprocess.Popen(args, env=env, stdout=log, stderr=subprocess.STDOUT,
                                              start_new_session=True, preexec_fn=_die_with_parent))
        cluster = SlurmCluster(root, conf, env)
        while not _node_idle(env):
            dead = [p.args[0] for p in processes if p.poll() is not None]
            if dead or time.monotonic() > deadline:
                _unavailable(f"the node did not come up ({', '.join(dead) or 'timeout'}):\n" + cluster.log_tail())
            time.sleep(0.3)
        yield cluster
        _drain(env)
    finally:
        _stop(processes, root)


@pytest.fixture(scope="session")
def slurm(tmp_path_factory) -> Iterator[SlurmCluster]:
    """A running one-node SLURM cluster (session-scoped); its clients need ``cluster.env``."""
    yield from start_cluster(tmp_path_factory.mktemp("slurm"))
