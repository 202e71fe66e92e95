"""Reading an MCAP file with the Foxglove ecosystem's own code (node: @mcap/core, @mcap/support,
@foxglove/schemas; see foxglove_node/check.cjs). The node packages are installed once from the lock
file into foxglove_node/node_modules; without node and npm the test is skipped, unless
MIDAS_REQUIRE_NODE=1 (.ci/run) turns that skip into a failure."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

CHECKER = Path(__file__).parent / "foxglove_node"


def _unavailable(reason: str) -> None:
    if os.environ.get("MIDAS_REQUIRE_NODE") == "1":
        pytest.fail(f"{reason} (MIDAS_REQUIRE_NODE=1)")
    pytest.skip(reason)


def _node_modules() -> None:
    if shutil.which("node") is None or shutil.which("npm") is None:
        _unavailable("node and npm are needed to read MCAP with Foxglove's packages")
    if (CHECKER / "node_modules" / "@mcap" / "core").is_dir():
        return
    done = subprocess.run(["npm", "ci", "--no-audit", "--no-fund", "--ignore-scripts"], cwd=CHECKER,
                          capture_output=True, text=True, timeout=300)
    if done.returncode != 0:
        _unavailable(f"npm ci failed in {CHECKER}: {done.stderr.strip()[-500:]}")


def read_with_foxglove(path: Path) -> dict[str, Any]:
    """``{"topics": {topic: {schema, encoding, count, first, last, first_log_time, metadata}},
    "metadata": [record names]}``; fails the test when a message does not decode or check."""
    _node_modules()
    done = subprocess.run(["node", "check.cjs", str(path)], cwd=CHECKER, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)
