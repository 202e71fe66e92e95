"""Small labelled sessions for the gesture-recognition tests, written through midas_cli.session only.

Each session has a 30 Hz video frame clock, frame labels (``labels/gestures.csv``) and an aligned
table (``derived/aligned.npz``) with EmHT sensor columns, MTM kinematics and a clutch column, whose
motion depends on the gesture: class k moves the hands along its own direction at its own frequency,
plus noise. Optionally ``derived/image_features.npz``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from midas_cli.clock import HostClock
from midas_cli.session.derived import AlignedTable, write_aligned
from midas_cli.session.labels import write_frame_labels
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
from midas_cli.session.writer import SessionMetadata, SessionWriter

VIDEO = StreamSpec("video", "video", (SEQ, T_HOST, Column("t_device_s", "float", "s", 6, clock="device")), 30.0)
CLASSES = ("G1", "G2", "G3", "G4")
FPS = 30.0


def gesture_sequence(rng: np.random.Generator, n_frames: int, n_classes: int) -> np.ndarray:
    """(n_frames,) class indices: consecutive gestures of 20-50 frames, never the same twice in a row."""
    labels, cls = [], int(rng.integers(n_classes))
    while len(labels) < n_frames:
        labels += [cls] * int(rng.integers(20, 50))
        cls = (cls + 1 + int(rng.integers(n_classes - 1))) % n_classes
    return np.asarray(labels[:n_frames])


def motion(labels: np.ndarray, rng: np.random.Generator, noise: float = 0.3) -> dict[str, np.ndarray]:
    """Aligned columns (name -> (N,)) whose pattern follows the class of each frame."""
    n = len(labels)
    t = np.arange(n) / FPS
    directions = np.random.default_rng(99).normal(size=(len(CLASSES), 4, 3))
    freq = 0.5 + np.arange(len(CLASSES))
    columns = {}
    for s in range(4):
        for a, axis in enumerate("xyz"):
            wave = np.sin(2 * np.pi * freq[labels] * t) * directions[labels, s, a] * 20
            columns[f"emht.s{s + 1}_{axis}_mm"] = 100 * s + wave + rng.normal(0, noise, n)
        for angle in ("azimuth", "elevation", "roll"):
            columns[f"emht.s{s + 1}_{angle}_deg"] = 30 * directions[labels, s, 0] + rng.normal(0, noise, n)
    for side, offset in (("left", 0), ("right", 2)):
        for axis in "xyz":
            columns[f"mtm.{side}_{axis}_mm"] = columns[f"emht.s{offset + 1}_{axis}_mm"] * 0.5
            columns[f"mtm.{side}_v{axis}_mm_s"] = np.gradient(columns[f"mtm.{side}_{axis}_mm"], t)
        for axis in "xyzw":
            columns[f"mtm.{side}_q{axis}"] = np.full(n, 0.5)
        columns[f"mtm.{side}_grasper_deg"] = 10.0 * labels
    columns["clutch"] = (np.arange(n) % 150 >= 140).astype(float)
    return columns


def write_gesture_session(root: Path, subject: str, trial: int, n_frames: int = 600, seed: int = 0,
                          platform: str = "davinci-xi", image_dim: int = 0, unlabelled_edges: int = 5) -> Path:
    """A finished session with labels and an aligned table; returns its folder."""
    rng = np.random.default_rng(seed)
    clock = HostClock.anchored_now()
    start = 1_700_000_000_000_000_000 + seed * 10**12
    writer = SessionWriter.create(root, SessionMetadata(subject, "demo", trial, platform), clock,
                                  {"video": {"kind": "test"}}, [VIDEO], start_ns=start)
    frame_ns = start + np.round(np.arange(n_frames) * 1e9 / FPS).astype(np.int64)
    writer.append("video", VIDEO.format_rows([(i, int(frame_ns[i]), i / FPS) for i in range(n_frames)]))
    writer.finalize("complete", "test", int(frame_ns[-1]) + 1, {})
    labels = gesture_sequence(rng, n_frames, len(CLASSES))
    names = np.array([CLASSES[k] for k in labels], dtype=object)
    names[:unlabelled_edges] = ""
    write_frame_labels(writer.folder, np.arange(n_frames), names, {"taxonomy": "test"})
    columns = motion(labels, rng)
    values = np.column_stack(list(columns.values()))
    write_aligned(writer.folder, AlignedTable(np.arange(n_frames), frame_ns, list(columns), values))
    if image_dim:
        features = np.eye(len(CLASSES), image_dim)[labels] + rng.normal(0, 0.1, (n_frames, image_dim))
        np.savez(writer.folder / "derived" / "image_features.npz", frame=np.arange(n_frames),
                 features=features.astype(np.float32), note="synthetic")
    return writer.folder


def write_gesture_dataset(root: Path, n_trials: int = 4, subjects: int = 2, **kwargs) -> list[Path]:
    return [write_gesture_session(root, str(1 + i % subjects), 1 + i, seed=i, **kwargs) for i in range(n_trials)]


def write_two_users(root: Path, n_frames: int) -> Path:
    """Users B and C with trials 1 and 2 each (four sessions, seeds 0..3) under ``root``: the smallest
    folder a leave-one-user-out run needs; returns ``root``."""
    for i, (user, trial) in enumerate((u, t) for u in "BC" for t in (1, 2)):
        write_gesture_session(root, user, trial, n_frames=n_frames, seed=i)
    return root


def write_louo_dataset(root: Path) -> Path:
    """Users B, C, D with trials 1 and 2 each, of uneven lengths (120..220 frames): the smallest dataset with
    three LOUO folds; returns ``root``."""
    for i, (user, trial) in enumerate((u, t) for u in "BCD" for t in (1, 2)):
        write_gesture_session(root, user, trial, n_frames=120 + 20 * i, seed=i)
    return root
