"""Shared helpers: run the real CLI in a subprocess; build small sessions through the library."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from midas_cli.clock import HostClock
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
from midas_cli.session.writer import SessionMetadata, SessionWriter

REPO = Path(__file__).resolve().parents[1]


def midas(*args: str, timeout: float = 120, check: bool = False, **kwargs) -> subprocess.CompletedProcess:
    """Run `python -m midas_cli ARGS` and capture stdout/stderr as text."""
    env = {**os.environ, "NO_COLOR": "1", "COLUMNS": "200"}
    result = subprocess.run([sys.executable, "-m", "midas_cli", *args], capture_output=True, text=True,
                            timeout=timeout, env=env, **kwargs)
    if check and result.returncode != 0:
        raise AssertionError(f"midas {' '.join(args)} exited {result.returncode}\n{result.stderr}")
    return result


SPEC = StreamSpec("demo", "demo", (SEQ, T_HOST, Column("x_mm", "float", "mm", 2)), 100.0)


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


@pytest.fixture
def small_session(tmp_path: Path) -> Path:
    return write_session(tmp_path)
