"""Writing files beside the streams of a finished session (calib/, derived/): JSON and NPZ.

Each write goes to a temporary file that is renamed into place, so a reader never sees half a file;
``relative`` must name a file inside the session folder (checked like manifest paths).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.session.manifest import check_inside


def _target(session_path: Path | str, relative: str) -> Path:
    path = check_inside(Path(session_path), relative)
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def write_json(session_path: Path | str, relative: str, document: Any) -> Path:
    """Write ``document`` as indented JSON to ``session/relative``."""
    path = _target(session_path, relative)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
    os.replace(tmp, path)
    return path


def write_npz(session_path: Path | str, relative: str, **arrays: np.ndarray) -> Path:
    """Write ``arrays`` as an uncompressed .npz to ``session/relative`` (loadable without pickle)."""
    path = _target(session_path, relative)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)
    return path
