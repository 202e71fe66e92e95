"""pytest hooks and fixtures; the helpers tests import live in tests/helpers/."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from helpers.cli import SHARED_DATA, write_session

pytest_plugins = ("helpers.trakstar",  # the `emulator` fixture (trakSTAR on a pty)
                  "helpers.slurm_fixture")  # the `slurm` fixture (a one-node SLURM, session-scoped)


def pytest_runtest_setup(item: pytest.Item) -> None:
    for marker in item.iter_markers("shared_data"):
        missing = [str(SHARED_DATA / part) for part in marker.args if not (SHARED_DATA / part).exists()]
        if not missing:
            continue
        if os.environ.get("MIDAS_REQUIRE_SHARED_DATA") == "1":
            pytest.fail(f"shared development data missing: {', '.join(missing)} (MIDAS_REQUIRE_SHARED_DATA=1 says "
                        f"this machine must have it)", pytrace=False)
        pytest.skip(f"shared development data not present: {', '.join(missing)} (it lives beside the repository in "
                    f"../shared/data; a user's clone has none)")


@pytest.fixture
def small_session(tmp_path: Path) -> Path:
    return write_session(tmp_path)
