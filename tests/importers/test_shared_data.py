"""Tests that read ../shared/data (development data, not part of the product) skip with a reason on a
user's clone, and fail where MIDAS_REQUIRE_SHARED_DATA=1 says the data must be there (CI, .ci/run)."""

from __future__ import annotations

import os
import subprocess
import sys

from helpers.cli import REPO


def _run(require: bool) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "MIDAS_REQUIRE_SHARED_DATA"}
    env["MIDAS_SHARED_DATA"] = "/nonexistent/shared-data"
    if require:
        env["MIDAS_REQUIRE_SHARED_DATA"] = "1"
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider",
                           "tests/importers/test_import.py::test_real_midas_folder_imports_and_verifies"],
                          cwd=REPO, capture_output=True, text=True, timeout=300, env=env)


def test_missing_shared_data_skips_with_its_path_on_a_users_clone() -> None:
    result = _run(require=False)
    assert result.returncode == 0 and "1 skipped" in result.stdout, result.stdout + result.stderr
    assert "/nonexistent/shared-data/midas-dcs-sample" in result.stdout


def test_missing_shared_data_fails_where_it_is_required() -> None:
    result = _run(require=True)
    assert result.returncode != 0 and "1 error" in result.stdout, result.stdout + result.stderr
    assert "MIDAS_REQUIRE_SHARED_DATA=1" in result.stdout
