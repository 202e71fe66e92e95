"""Writing files beside the streams of a finished session (calib/, derived/, logs/): JSON and NPZ.

Each write goes through ``outputs``: ``relative`` must resolve inside the session folder (no link out),
and the file is written to a unique temporary renamed into place under the session lock, so a reader
never sees half a file.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.session.outputs import inside_session, replacing


def write_json(session_path: Path | str, relative: str, document: Any) -> Path:
    """Write ``document`` as indented JSON to ``session/relative``."""
    path = inside_session(session_path, relative)
    with replacing(path) as tmp:
        tmp.write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
    return path


def write_npz(session_path: Path | str, relative: str, **arrays: np.ndarray) -> Path:
    """Write ``arrays`` as an uncompressed .npz to ``session/relative`` (loadable without pickle)."""
    path = inside_session(session_path, relative)
    with replacing(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)  # type: ignore[arg-type]  # numpy's stub types **kwds as savez's allow_pickle
    return path
