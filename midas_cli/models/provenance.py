"""Where a trained model came from: the midas version, the model sources' digest and the git commit."""

from __future__ import annotations

import hashlib
import subprocess
from pathlib import Path

from midas_cli import __version__


def code_version(torch_version: str) -> dict:
    """midas version, sha256 of the model package sources, the git commit when available, and torch's."""
    package = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for source in sorted(package.glob("*.py")):
        digest.update(source.name.encode() + source.read_bytes())
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=package, capture_output=True, text=True,
                                timeout=5).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    return {"midas": __version__, "models_sha256": digest.hexdigest(), "git_commit": commit,
            "torch": str(torch_version)}
