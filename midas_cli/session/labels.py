"""Frame labels stored in a session: ``labels/<name>.csv`` + ``labels/<name>.json`` (provenance).

Frame convention (stated once, used everywhere): ``frame`` is the 0-based video frame index, i.e. the
``seq`` value of the session's ``video`` stream (frame 0 = the first frame of the recording). An empty
label means "unlabelled" (not the same as an explicit Idle class). The manifest is the record of the
acquisition and is not rewritten; label sets live beside it and say where they came from.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd

from midas_cli import __version__
from midas_cli.errors import SessionError
from midas_cli.session.names import check_name
from midas_cli.session.outputs import replacing, session_lock, session_target

LABELS_DIR = "labels"
FRAME_CONVENTION = "0-based video frame index = seq of the session's video stream"


@dataclass
class FrameLabels:
    """One label per frame: ``frames`` (N,) int64 ascending, ``labels`` (N,) str ('' = unlabelled)."""

    frames: np.ndarray
    labels: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def classes(self) -> list[str]:
        return sorted(set(self.labels.tolist()) - {""})


def write_frame_labels(session_path: Path | str, frames: Sequence[int], labels: Sequence[str],
                       meta: dict[str, Any], name: str = "gestures") -> Path:
    """Write (replace) label set ``name``; ``meta`` should name the taxonomy and the source."""
    check_name(name, "label set", "label set name")
    frame_array = np.asarray(frames, dtype=np.int64)
    label_array = np.asarray(labels, dtype=object)
    if frame_array.shape != label_array.shape or frame_array.ndim != 1:
        raise SessionError(f"frames {frame_array.shape} and labels {label_array.shape} must be equal-length 1-D")
    if len(frame_array) > 1 and not (np.diff(frame_array) > 0).all():
        raise SessionError("label frames must be strictly increasing")
    csv_path = session_target(session_path, f"{LABELS_DIR}/{name}.csv")
    json_path = session_target(session_path, f"{LABELS_DIR}/{name}.json")
    full_meta = {"frame_convention": FRAME_CONVENTION, "midas_version": __version__, **meta,
                 "frames": int(len(frame_array))}
    with session_lock(session_path), replacing(json_path) as tmp_json, replacing(csv_path) as tmp_csv:
        pd.DataFrame({"frame": frame_array, "label": label_array}).to_csv(tmp_csv, index=False)
        tmp_json.write_text(json.dumps(full_meta, indent=2) + "\n", encoding="utf-8")
    return csv_path


def label_set_files(session_path: Path | str, name: str) -> tuple[Path, Path]:
    """``labels/<name>.csv`` and ``labels/<name>.json`` of the session (the label set and its provenance)."""
    folder = Path(session_path) / LABELS_DIR
    return folder / f"{check_name(name, 'label set', 'label set name')}.csv", folder / f"{name}.json"


def read_frame_labels(session_path: Path | str, name: str = "gestures") -> FrameLabels:
    """Label set ``name`` of the session (SessionError when it is missing, misnamed or malformed)."""
    csv_path, meta_path = label_set_files(session_path, name)
    if not csv_path.is_file():
        if csv_path.exists():  # a folder, FIFO or device: never opened (a read could block for ever)
            raise SessionError(f"{csv_path}: not a regular file (a label set is a frame,label CSV)")
        have = ", ".join(list_label_sets(session_path)) or "none"
        raise SessionError(f"{session_path} has no label set {name!r} (label sets: {have})")
    frame = _read_label_csv(csv_path)
    meta = _read_label_meta(meta_path) if meta_path.is_file() else {}
    return FrameLabels(frame["frame"].to_numpy(), frame["label"].to_numpy(dtype=object), meta)


def _read_label_csv(csv_path: Path) -> pd.DataFrame:
    """``frame,label`` rows; anything else is a SessionError naming the file."""
    try:
        frame = pd.read_csv(csv_path, dtype=str, keep_default_na=False, encoding="utf-8")
    except (ValueError, UnicodeDecodeError, pd.errors.ParserError) as exc:  # EmptyDataError is a ValueError
        raise SessionError(f"{csv_path}: not a frame,label CSV ({exc})") from None
    if not {"frame", "label"} <= set(frame.columns):
        raise SessionError(f"{csv_path}: expected columns frame,label, got {','.join(map(str, frame.columns))}")
    try:
        frames = frame["frame"].astype("int64")
    except (ValueError, OverflowError):
        raise SessionError(f"{csv_path}: column 'frame' must hold whole frame numbers") from None
    return pd.DataFrame({"frame": frames, "label": frame["label"]})


def _read_label_meta(meta_path: Path) -> dict[str, Any]:
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:  # JSONDecodeError is a ValueError
        raise SessionError(f"{meta_path}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise SessionError(f"{meta_path}: expected a JSON object, got {type(meta).__name__}")
    return meta


def list_label_sets(session_path: Path | str) -> list[str]:
    """Names of the session's label sets (``labels/<name>.csv``), sorted; SessionError when a file there
    has a name no label set may have (it would name files of exports)."""
    folder = Path(session_path) / LABELS_DIR
    names = sorted(p.name[:-len(".csv")] for p in folder.glob("*.csv")) if folder.is_dir() else []
    for name in names:
        check_name(name, "label set", f"the name of a label set in {folder} (<name>.csv)")
    return names
