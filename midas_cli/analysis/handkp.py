"""Offline hand keypoints from a recorded stereo video: ``midas extract handkp SESSION``.

For every frame of the stereo device's ``<device>`` stream: read the side-by-side frame from
``video/``, detect the thumb and middle fingertips of each hand in the left image (a pluggable
detector), and turn each into a 3-D point in the left camera frame (mm) with StereoSGBM depth from
the calibration in ``calib/<device>.conf`` (:mod:`~midas_cli.devices.rgbd.stereo`). The result is a
HandKP stream with the layout of the simulated one (``sim://handkp``): a hand the detector missed has
empty fields and ``<hand>_detected`` 0; a fingertip without a valid disparity is empty. Never zeros.

Detectors:
  * ``mediapipe`` -- MediaPipe Hands (landmarks 4 = thumb tip, 12 = middle-finger tip). MediaPipe is an
    optional extra: its last wheel bundling the hand model (0.10.21) needs numpy<2, so it runs in its own
    environment (see README, "Hand keypoints"); it is imported only here, when asked for.
  * ``truth`` -- for ``sim://rgbd`` sessions: the rendered true fingertips projected into the left image
    (what a perfect 2-D detector would report; fingertips hidden behind a nearer one are not reported),
    so the depth and 3-D geometry can be checked against ground truth.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Protocol

import numpy as np
import pandas as pd

from midas_cli import __version__
from midas_cli.devices.rgbd.calibration import RESOLUTIONS, Rectifier, StereoCalibration, parse_zed_conf
from midas_cli.devices.rgbd.device import HANDS, KEYPOINTS, calibration_file, keypoint_columns, video_file
from midas_cli.errors import ConfigError, SessionError
from midas_cli.session.device_files import add_stream
from midas_cli.session.reader import Session
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec

log = logging.getLogger(__name__)

DETECTORS = ("mediapipe", "truth")
MEDIAPIPE_TIPS = (4, 12)  # THUMB_TIP, MIDDLE_FINGER_TIP


class KeypointDetector(Protocol):
    """Finds fingertips in the left image: {hand: (2 keypoints (thumb, middle), 2) px}, NaN for unseen ones;
    a hand that was not found is left out."""

    def detect(self, seq: int, left_bgr: np.ndarray) -> dict[str, np.ndarray]: ...


def handkp_spec(name: str, rate_hz: float) -> StreamSpec:
    """The HandKP stream layout (as ``sim://handkp``)."""
    columns = [SEQ, T_HOST, Column("t_device_ns", "int", "ns", clock="device", description="camera timestamp")]
    per_hand = keypoint_columns()
    for h, hand in enumerate(HANDS):
        columns += per_hand[6 * h:6 * h + 6]
        columns.append(Column(f"{hand}_detected", "int", "bool", description="1 if the hand was detected"))
    return StreamSpec(name, name, tuple(columns), rate_hz, "hand keypoints from RGB-D (midas extract handkp)")


class TruthDetector:
    """Projects a simulated session's true fingertips (``<device>_truth``) into the left image."""

    def __init__(self, session: Session, device: str, calib: StereoCalibration) -> None:
        from midas_cli.synthetic.stereo_camera import occluded, project_left

        truth = session.read_stream(f"{device}_truth")
        values = truth[[c.name for c in keypoint_columns()]].to_numpy(dtype=float).reshape(-1, 2, 2, 3)
        self.pixels: dict[int, dict[str, np.ndarray]] = {}
        for seq, points in zip(truth["seq"].tolist(), values):  # points (2 hands, 2 keypoints, 3)
            hidden = occluded(points.reshape(4, 3)).reshape(2, 2)
            px = project_left(calib, points.reshape(4, 3)).reshape(2, 2, 2)
            px[hidden] = np.nan
            self.pixels[seq] = {hand: px[h] for h, hand in enumerate(HANDS)}

    def detect(self, seq: int, left_bgr: np.ndarray) -> dict[str, np.ndarray]:
        return self.pixels.get(seq, {})


class MediaPipeDetector:
    """MediaPipe Hands on the left image. Its handedness assumes a mirrored (selfie) image: for a camera
    looking at the hands (not mirrored) the labels are swapped back unless ``mirrored``."""

    def __init__(self, mirrored: bool = False, min_confidence: float = 0.5) -> None:
        try:
            import mediapipe as mp
        except ImportError:
            raise ConfigError("the mediapipe detector needs MediaPipe, which is not installed in this environment; "
                              "create the hand-keypoint environment (README, 'Hand keypoints': a venv with "
                              "mediapipe==0.10.21 and numpy<2) and run `midas extract handkp` from it, or use "
                              "--detector truth on simulated sessions") from None
        self.hands = mp.solutions.hands.Hands(static_image_mode=False, max_num_hands=2, model_complexity=1,
                                              min_detection_confidence=min_confidence)
        self.mirrored = mirrored

    def detect(self, seq: int, left_bgr: np.ndarray) -> dict[str, np.ndarray]:
        import cv2

        h, w = left_bgr.shape[:2]
        result = self.hands.process(cv2.cvtColor(left_bgr, cv2.COLOR_BGR2RGB))
        found: dict[str, np.ndarray] = {}
        for landmarks, handedness in zip(result.multi_hand_landmarks or [], result.multi_handedness or []):
            label = handedness.classification[0].label.lower()
            hand = label if self.mirrored else {"left": "right", "right": "left"}[label]
            found[hand] = np.array([[landmarks.landmark[i].x * w, landmarks.landmark[i].y * h] for i in MEDIAPIPE_TIPS])
        return found


@dataclass
class ExtractResult:
    """What an extraction produced."""

    session: Path
    device: str
    stream: str
    frames: int = 0
    detected: dict[str, int] = field(default_factory=lambda: {hand: 0 for hand in HANDS})
    keypoints_with_depth: int = 0

    def to_json(self) -> dict:
        return {"session": str(self.session), "device": self.device, "stream": self.stream, "frames": self.frames,
                "detected": self.detected, "keypoints_with_depth": self.keypoints_with_depth}


def stereo_device(session: Session, device: str | None) -> str:
    """The stereo camera device of the session (the only one, or the one named)."""
    cameras = [name for name, entry in session.manifest["devices"].items()
               if "calibration" in (entry.get("settings") or {})]
    if device is not None:
        if device not in cameras:
            raise ConfigError(f"{session.path}: {device!r} is no stereo camera device (stereo devices: "
                              f"{', '.join(cameras) or 'none'})")
        return device
    if len(cameras) != 1:
        raise ConfigError(f"{session.path}: {len(cameras)} stereo camera devices ({', '.join(cameras) or 'none'}); "
                          f"name one with --device")
    return cameras[0]


def session_calibration(session: Session, device: str) -> StereoCalibration:
    """The calibration copied into the session at recording time."""
    path = session.path / calibration_file(device)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise SessionError(f"{session.path}: calibration {calibration_file(device)} unreadable: "
                           f"{exc.strerror}") from None
    resolution = next((r for r in RESOLUTIONS if f"[LEFT_CAM_{r}]" in text), "HD")
    return parse_zed_conf(text, resolution, str(path))


def make_detector(name: str, session: Session, device: str, calib: StereoCalibration,
                  mirrored: bool = False) -> KeypointDetector:
    if name == "truth":
        return TruthDetector(session, device, calib)
    if name == "mediapipe":
        return MediaPipeDetector(mirrored)
    raise ConfigError(f"unknown detector {name!r} (detectors: {', '.join(DETECTORS)})")


def extract_handkp(session_path: Path | str, detector: str = "mediapipe", device: str | None = None,
                   stream: str = "handkp", replace: bool = False, mirrored: bool = False,
                   progress: Callable[[int, int], None] | None = None) -> ExtractResult:
    """Detect fingertips in every recorded stereo frame, lift them to 3-D and add the HandKP stream."""
    from midas_cli.devices.rgbd.stereo import keypoints_3d

    session = Session.open(session_path)
    device = stereo_device(session, device)
    calib = session_calibration(session, device)
    rectifier = Rectifier(calib)
    finder = make_detector(detector, session, device, calib, mirrored)
    frames = session.read_stream(device)
    result = ExtractResult(session.path, device, stream)
    rows = []
    for seq, t_host, t_device, image in iter_frames(session, device, frames):
        rows.append(_frame_row(finder, rectifier, keypoints_3d, seq, t_host, t_device, image, calib.size[0], result))
        if progress is not None:
            progress(len(rows), len(frames))
    spec = handkp_spec(stream, session.stream_spec(device).nominal_rate_hz)
    add_stream(session.path, spec, rows, {"step": "midas extract handkp", "detector": detector, "source": device,
                                          "calibration": calibration_file(device), "midas_version": __version__},
               replace=replace)
    return result


def _frame_row(finder: KeypointDetector, rectifier: Rectifier, lift, seq: int, t_host: int, t_device,
               image: np.ndarray, eye_width: int, result: ExtractResult) -> tuple:
    left, right = image[:, :eye_width], image[:, eye_width:]
    found = finder.detect(seq, left)
    values: list = [None if t_device is None else int(t_device)]
    for hand in HANDS:
        px = found.get(hand)
        if px is None or not np.isfinite(px).any():
            values += [float("nan")] * 6 + [0]
            continue
        points = np.full((len(KEYPOINTS), 3), np.nan)
        seen = np.isfinite(px).all(axis=1)
        points[seen] = lift(rectifier, left, right, px[seen])
        result.detected[hand] += 1
        result.keypoints_with_depth += int(np.isfinite(points).all(axis=1).sum())
        values += points.reshape(6).tolist() + [1]
    result.frames += 1
    return (seq, t_host, *values)


def iter_frames(session: Session, device: str, frames):
    """(seq, t_host_ns, t_device_ns or None, side-by-side BGR image) of every row of the frame stream, read
    from the device's video files in order; SessionError if a file holds fewer frames than its rows."""
    import cv2

    for file_index, rows in frames.groupby("file", sort=True):
        path = session.path / video_file(device, int(file_index))
        capture = cv2.VideoCapture(str(path))
        if not capture.isOpened():
            raise SessionError(f"{session.path}: cannot read {video_file(device, int(file_index))}")
        position = 0
        try:
            for seq, t_host, t_device, frame in zip(rows["seq"], rows["t_host_ns"], rows["t_device_ns"], rows["frame"]):
                while position <= int(frame):
                    ok, image = capture.read()
                    if not ok:
                        raise SessionError(f"{path}: ends before frame {int(frame)} (the stream lists it)")
                    position += 1
                yield int(seq), int(t_host), (None if pd.isna(t_device) else int(t_device)), image
        finally:
            capture.release()
