"""Run the real CLI in a subprocess, wait for what it records, build small sessions through the library."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from midas_cli.clock import HostClock
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
from midas_cli.session.writer import SessionMetadata, SessionWriter

REPO = Path(__file__).resolve().parents[2]
# The MiDAS sample files and real gesture labels: development data beside the repository (../shared/data),
# not part of the product. Tests marked `shared_data` skip without it on a user's clone; CI sets
# MIDAS_REQUIRE_SHARED_DATA=1 (.ci/run), which turns that skip into a failure.
SHARED_DATA = Path(os.environ.get("MIDAS_SHARED_DATA", REPO.parent / "shared" / "data"))


def midas(*args: str, timeout: float = 120, check: bool = False, env: dict[str, str] | None = None,
          **kwargs) -> subprocess.CompletedProcess:
    """Run `python -m midas_cli ARGS` and capture stdout/stderr as text (``env`` added to the environment)."""
    env = {**os.environ, "NO_COLOR": "1", "COLUMNS": "200", **(env or {})}
    result = subprocess.run([sys.executable, "-m", "midas_cli", *args], capture_output=True, text=True,
                            timeout=timeout, env=env, **kwargs)
    if check and result.returncode != 0:
        raise AssertionError(f"midas {' '.join(args)} exited {result.returncode}\n{result.stderr}")
    return result


def wait_for(predicate, timeout_s: float = 60.0, step_s: float = 0.002):
    """``predicate()``'s first true value, polled every ``step_s`` for up to ``timeout_s`` (AssertionError
    after that)."""
    import time

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(step_s)
    raise AssertionError("timed out waiting")


SPEC = StreamSpec("demo", "demo", (SEQ, T_HOST, Column("x_mm", "float", "mm", 2)), 100.0)


def stream_rows(out: Path, stream: str) -> int:
    """Data rows of ``stream`` in the (only) session under ``out`` so far (0 before it exists)."""
    files = list(Path(out).glob(f"*/streams/{stream}.csv"))
    return max(0, files[0].read_bytes().count(b"\n") - 1) if files else 0


def last_seq(out: Path, stream: str) -> int:
    """The last complete row's seq of ``stream`` in the (only) session under ``out`` (-1: none yet)."""
    files = list(Path(out).glob(f"*/streams/{stream}.csv"))
    lines = files[0].read_bytes().split(b"\n")[1:-1] if files else []
    return int(lines[-1].split(b",", 1)[0]) if lines else -1


def record_until(out: Path, args: list[str], rows: dict[str, int] | None = None, timeout: float = 180,
                 until=None) -> subprocess.CompletedProcess:
    """`midas record ARGS --out OUT` with no --duration, stopped with Ctrl-C (SIGINT) once every stream
    in ``rows`` has at least that many rows on disk (and ``until(out)`` is true, if given): a test that
    needs data from every device waits for it instead of assuming how fast the devices open."""
    rows = rows or {}
    import signal
    import time

    env = {**os.environ, "NO_COLOR": "1", "COLUMNS": "200"}
    process = subprocess.Popen([sys.executable, "-m", "midas_cli", "record", *args, "--out", str(out)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + timeout
    try:
        while not (all(stream_rows(out, name) >= n for name, n in rows.items()) and (until is None or until(out))):
            if process.poll() is not None or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=60)
    except BaseException:
        process.kill()
        raise
    return subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)


def write_session(root: Path, rows: int = 50, status: str = "complete", seq_step: int = 1) -> Path:
    """A small finished session with one stream `demo` (seq, t_host_ns, x_mm) at 100 Hz."""
    clock = HostClock.anchored_now()
    writer = SessionWriter.create(root, SessionMetadata("7", "demo", 1), clock, {"demo": {"kind": "test"}}, [SPEC])
    t0 = clock.now_ns()
    data = [(i * seq_step, t0 + i * 10_000_000, i * 0.5) for i in range(rows)]
    writer.append("demo", SPEC.format_rows(data))
    extra = {"demo": {"missing_explained": {"outage": (seq_step - 1) * (rows - 1)}}}
    writer.finalize(status, "test", t0 + rows * 10_000_000, extra)
    return writer.folder


def simulate_trial(out: Path, *options: str) -> Path:
    """One 5-s simulated Raven-II trial (seed 3) under ``out`` (``options``: more `simulate dataset`
    options); its session folder."""
    result = midas("simulate", "dataset", "--platform", "raven-ii", "--trials", "1", "--max-seconds", "5",
                   "--seed", "3", *options, "--out", str(out), check=True)
    return Path(result.stdout.strip().splitlines()[-1])


def copy_session(session: Path, into: Path) -> Path:
    """A copy of ``session`` in the folder ``into`` (a test may then damage it)."""
    import shutil

    return Path(shutil.copytree(session, into / session.name))
