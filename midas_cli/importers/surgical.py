"""Import JIGSAWS and COMPASS trials (kinematics + gesture transcriptions) as v1 sessions.

* JIGSAWS ``kinematics/AllGestures/<Task>_<X###>.txt``: 76 space-separated values per line at 30 Hz;
  per manipulator (MTM left 1-19, MTM right 20-38, PSM left 39-57, PSM right 58-76): tool-tip position
  xyz (m), rotation matrix (9, row-major), linear velocity xyz (m/s), angular velocity xyz (rad/s),
  gripper angle (rad).
* COMPASS ``kinematics/<Task>_S##_T##.csv``: 32 comma-separated columns with a header; MTML, MTMR, PSML,
  PSMR each position xyz (m), orientation quaternion xyzw, gripper angle (rad); velocity is derived here
  by central differences.
* Transcriptions ``<same stem>.txt`` in ``transcriptions/`` (JIGSAWS) or ``gestures/`` (COMPASS):
  ``start end Gk`` at 30 Hz, inclusive; frames outside every segment are unlabelled.
Each trial becomes a session with streams ``video`` (frame clock: kinematic row k = frame k at 30 Hz;
the sources have no host clock, so host time = a fixed epoch + k / 30 s), ``mtm`` and ``psm``
(``kinematics_spec``, mm, quaternion xyzw, mm/s, degrees; clutch not recorded -> empty) and frame labels.
Each source is one entry of ``SOURCES`` (file pattern, line shape, readers, transcription folders).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from midas_cli.analysis.kinematics_schema import kinematics_spec
from midas_cli.errors import ConfigError, SessionError
from midas_cli.geometry import quaternions_from_matrices
from midas_cli.importers.common import file_facts, write_session
from midas_cli.labels.segments import FrameSegment
from midas_cli.labels.transcription import read_transcription
from midas_cli.session.labels import write_frame_labels
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
from midas_cli.session.writer import SessionMetadata

RATE_HZ = 30.0
EPOCH_NS = 1_262_304_000_000_000_000  # 2010-01-01T00:00:00Z: stands in for the missing host clock
_STEM = re.compile(r"^(?P<task>[A-Za-z-]+(?:_[A-Za-z-]+)*?)_(?:S(?P<s>\d+)_T(?P<t>\d+)|(?P<letter>[A-Z])(?P<n>\d{3}))$")
ARMS = (("mtm", "left"), ("mtm", "right"), ("psm", "left"), ("psm", "right"))
Arm = dict[str, np.ndarray]


@dataclass(frozen=True)
class SourceFormat:
    """One source of kinematics and transcriptions: its ``name`` (``import://NAME/...`` in the session,
    the taxonomy's prefix), ``title``, the kinematics file ``pattern`` (under a ``kinematics`` folder),
    ``width`` values per data line (one block of ``width / 4`` per arm, in ``ARMS`` order), whether line 1
    is a ``header``, the value ``separator`` (None: white space), the folders that hold transcriptions
    (first found wins), ``read`` (file -> table (N, width)) and ``arm`` (one arm's block -> position (N, 3)
    mm, quaternion (N, 4), velocity (N, 3) mm/s, grasper (N,) deg)."""

    name: str
    title: str
    pattern: str
    width: int
    header: bool
    separator: str | None
    label_dirs: tuple[str, ...]
    read: Callable[[Path], np.ndarray]
    arm: Callable[[np.ndarray], Arm]


def kinematics_files(folder: Path, fmt: str) -> list[Path]:
    pattern = SOURCES[fmt].pattern
    files = sorted(p for p in folder.rglob(pattern) if "kinematics" in p.parts)
    if not files:
        raise SessionError(f"{folder} holds no {fmt} kinematics files (looked for kinematics/**/{pattern})")
    return files


def shape_discontinuities(path: Path, fmt: str) -> list[dict[str, Any]]:
    """Every data line whose value count is not the format's (a partial line, another column block):
    {file, line, what}. The sources have no host clock, so row shape is the only order check."""
    source = SOURCES[fmt]
    found = []
    with open(path, encoding="utf-8") as fh:
        for number, line in enumerate(fh, start=1):
            if not line.strip() or (source.header and number == 1):
                continue
            values = len(line.split(source.separator))
            if values != source.width:
                found.append({"file": path.name, "line": number,
                              "what": f"{values} values where {fmt} kinematics have {source.width} (partial line?)"})
    return found


def read_arms(path: Path, fmt: str) -> dict[tuple[str, str], Arm]:
    """Per (robot, side): position (N, 3) mm, quaternion (N, 4), velocity (N, 3) mm/s, grasper (N,) deg.
    A file with a line of the wrong shape is refused, naming every such line."""
    found = shape_discontinuities(path, fmt)
    if found:
        shown = "; ".join(f"line {d['line']}: {d['what']}" for d in found[:5])
        more = f" (and {len(found) - 5} more)" if len(found) > 5 else ""
        raise SessionError(f"{path}: rows of the wrong shape, {shown}{more}: fix or remove those lines, "
                           "the rows around them would otherwise be shifted in time")
    source = SOURCES[fmt]
    table = source.read(path)
    if table.shape[1] != source.width:
        raise SessionError(f"{path}: {table.shape[1]} columns per line, {source.title} kinematics have {source.width}")
    block = source.width // len(ARMS)
    return {arm: source.arm(table[:, block * i:block * (i + 1)]) for i, arm in enumerate(ARMS)}


def _read_jigsaws(path: Path) -> np.ndarray:
    return pd.read_csv(path, sep=r"\s+", header=None, engine="python").to_numpy(float)


def _jigsaws_arm(block: np.ndarray) -> Arm:
    rotation = block[:, 3:12].reshape(-1, 3, 3)
    return {"position": block[:, :3] * 1000.0, "quaternion": quaternions_from_matrices(rotation),
            "velocity": block[:, 12:15] * 1000.0, "grasper": np.degrees(block[:, 18])}


def _read_compass(path: Path) -> np.ndarray:
    return pd.read_csv(path).to_numpy(float)


def _compass_arm(block: np.ndarray) -> Arm:
    position = block[:, :3] * 1000.0
    quaternion = block[:, 3:7] / np.linalg.norm(block[:, 3:7], axis=1, keepdims=True)
    velocity = np.gradient(position, 1.0 / RATE_HZ, axis=0) if len(position) > 1 else np.zeros_like(position)
    return {"position": position, "quaternion": quaternion, "velocity": velocity, "grasper": np.degrees(block[:, 7])}


SOURCES = {source.name: source for source in (
    SourceFormat("jigsaws", "JIGSAWS", "*.txt", 76, False, None, ("transcriptions",), _read_jigsaws, _jigsaws_arm),
    SourceFormat("compass", "COMPASS", "*.csv", 32, True, ",", ("gestures", "transcriptions"), _read_compass,
                 _compass_arm),
)}


def transcription_for(kinematics: Path, root: Path, fmt: str) -> Path | None:
    for folder in SOURCES[fmt].label_dirs:
        for candidate in root.rglob(f"{folder}/{kinematics.stem}.txt"):
            return candidate
    return None


def frame_labels(segments: list[FrameSegment], frames: int) -> np.ndarray:
    """(frames,) labels: each segment's label on its inclusive frame range, '' elsewhere."""
    labels = np.full(frames, "", dtype=object)
    for segment in segments:
        labels[segment.first:min(segment.last, frames - 1) + 1] = segment.label
    return labels


def import_trial(path: Path, root: Path, fmt: str, out_root: Path) -> tuple[Path, dict[str, Any]]:
    match = _STEM.match(path.stem)
    if not match:
        raise SessionError(f"{path.name}: cannot read task/subject/trial from the name "
                           "(expected <Task>_S##_T## or <Task>_<Letter>###)")
    task = match["task"].replace("_", "-").lower()
    subject, trial = (match["s"], int(match["t"])) if match["s"] else (match["letter"], int(match["n"]))
    arms = read_arms(path, fmt)
    n = len(arms[ARMS[0]]["position"])
    k = np.arange(n, dtype=np.int64)
    host = EPOCH_NS + np.round(k * 1e9 / RATE_HZ).astype(np.int64)
    video = StreamSpec("video", "video", (SEQ, T_HOST, Column("t_device_s", "float", "s", 6, clock="device")),
                       RATE_HZ, "frame clock (kinematic row k = frame k)")
    streams = [(video, [k, host, k / RATE_HZ])]
    for robot in ("mtm", "psm"):
        columns: list[np.ndarray] = [k, host, k / RATE_HZ]
        for side in ("left", "right"):
            arm = arms[(robot, side)]
            columns += [*arm["position"].T, *arm["quaternion"].T, *arm["velocity"].T, arm["grasper"]]
        streams.append((kinematics_spec(robot, RATE_HZ), columns + [np.full(n, np.nan)]))
    report: dict[str, Any] = {"format": fmt, "kinematics": file_facts(path), "rows": n,
                              "clock": "no host clock in the source: t_host_ns = 2010-01-01 + frame / 30 Hz",
                              "clutch": "not recorded by the source: empty", "discontinuities": []}
    devices = {"video": {"kind": "video", "url": f"import://{fmt}/{path.name}", "streams": ["video"]},
               "robot": {"kind": "davinci", "url": f"import://{fmt}/{path.name}", "streams": ["mtm", "psm"]}}
    metadata = SessionMetadata(subject, task, trial, "davinci", f"imported from {fmt} {path.name}")
    transcription = transcription_for(path, root, fmt)
    report["transcription"] = file_facts(transcription) if transcription else "none found: no labels written"
    session = write_session(out_root, metadata, devices, streams, report)
    if transcription:
        segments = read_transcription(transcription, index_base=0)  # the file's frame k is kinematic row k
        write_frame_labels(session, k, frame_labels(segments, n), {
            "taxonomy": f"{fmt}-{task}", "source": str(transcription), "segments": len(segments)})
    return session, report


def import_surgical(folder: Path | str, out_root: Path | str, fmt: str) -> list[tuple[Path, dict[str, Any]]]:
    """Import every kinematics file under ``folder``; returns (session path, report) per trial."""
    if fmt not in SOURCES:
        raise ConfigError(f"format {fmt!r} unknown (expected {' or '.join(SOURCES)})")
    root = Path(folder)
    if not root.is_dir():
        raise SessionError(f"{root} is not a folder")
    return [import_trial(path, root, fmt, Path(out_root)) for path in kinematics_files(root, fmt)]
