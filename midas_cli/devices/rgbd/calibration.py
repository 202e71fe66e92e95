"""The ZED factory calibration file (``SN<serial>.conf``) and stereo rectification with OpenCV.

The file is INI text with one section per eye and resolution, ``[LEFT_CAM_HD]`` / ``[RIGHT_CAM_HD]``
(fx, fy, cx, cy in pixels; k1, k2, p1, p2, k3 Brown-Conrady distortion), and ``[STEREO]``: Baseline
(mm), TY, TZ (mm) and the rotation ``RX_HD``, ``CV_HD`` (about y, the convergence), ``RZ_HD`` (radians).

Convention used here (as Stereolabs' OpenCV samples): the right camera's centre is at
C = (Baseline, TY, TZ) mm in the left camera's frame and R = Rodrigues(RX, CV, RZ) maps left-camera
coordinates to right-camera coordinates, so X_right = R X_left + T with T = -R C. Camera frames are
OpenCV's: x right, y down, z forward (optical axis), millimetres. "The camera frame" of keypoints is the
(unrectified) left camera's.
"""

from __future__ import annotations

import configparser
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from midas_cli.errors import ConfigError

RESOLUTIONS = {"2K": (2208, 1242), "FHD": (1920, 1080), "HD": (1280, 720), "VGA": (672, 376)}
DIST_KEYS = ("k1", "k2", "p1", "p2", "k3")
UNDISTORT_CRITERIA = (3, 50, 1e-10)  # cv2.TERM_CRITERIA_COUNT | EPS: iterate to 1e-10 (default is 5 steps)


@dataclass(frozen=True)
class EyeIntrinsics:
    """Pinhole intrinsics (pixels) and Brown-Conrady distortion (k1, k2, p1, p2, k3) of one eye."""

    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=float)


@dataclass(frozen=True)
class StereoCalibration:
    """One resolution of a ZED calibration: per-eye intrinsics, stereo extrinsics, image size per eye."""

    left: EyeIntrinsics
    right: EyeIntrinsics
    baseline_mm: float
    ty_mm: float
    tz_mm: float
    rotation_rvec: tuple[float, float, float]  # (RX, CV, RZ) radians
    size: tuple[int, int]  # (width, height) of one eye
    serial: str = ""
    resolution: str = "HD"

    @property
    def rotation(self) -> np.ndarray:
        """R (3, 3): left-camera coordinates -> right-camera coordinates."""
        import cv2

        return cv2.Rodrigues(np.asarray(self.rotation_rvec, dtype=float))[0]

    @property
    def right_centre(self) -> np.ndarray:
        """The right camera's centre (3,) in the left camera frame, mm."""
        return np.array([self.baseline_mm, self.ty_mm, self.tz_mm])

    @property
    def translation(self) -> np.ndarray:
        """T (3,) mm with X_right = R X_left + T."""
        return -self.rotation @ self.right_centre

    def to_conf(self) -> str:
        """This calibration as ZED ``SN*.conf`` text (only this resolution's sections)."""
        r = self.resolution
        lines = []
        for side, eye in (("LEFT", self.left), ("RIGHT", self.right)):
            lines.append(f"[{side}_CAM_{r}]")
            lines += [f"fx={eye.fx!r}", f"fy={eye.fy!r}", f"cx={eye.cx!r}", f"cy={eye.cy!r}"]
            lines += [f"{k}={v!r}" for k, v in zip(DIST_KEYS, eye.dist)]
        rx, cv, rz = self.rotation_rvec
        lines += ["[STEREO]", f"Baseline={self.baseline_mm!r}", f"TY={self.ty_mm!r}", f"TZ={self.tz_mm!r}",
                  f"CV_{r}={cv!r}", f"RX_{r}={rx!r}", f"RZ_{r}={rz!r}", "[MISC]", "Sensor_ID=0"]
        return "\n".join(lines) + "\n"


def parse_zed_conf(text: str, resolution: str = "HD", source: str = "calibration") -> StereoCalibration:
    """Parse ZED ``SN*.conf`` text for one resolution (2K, FHD, HD, VGA); ConfigError naming what is missing."""
    if resolution not in RESOLUTIONS:
        raise ConfigError(f"ZED resolution {resolution!r} unknown (known: {', '.join(RESOLUTIONS)})")
    parser = configparser.ConfigParser()
    parser.optionxform = str
    try:
        parser.read_string(text)
        left, right = (_eye(parser, f"{side}_CAM_{resolution}") for side in ("LEFT", "RIGHT"))
        stereo = parser["STEREO"]
        rvec = tuple(float(stereo.get(f"{k}_{resolution}", 0.0)) for k in ("RX", "CV", "RZ"))
        return StereoCalibration(left, right, float(stereo["Baseline"]), float(stereo.get("TY", 0.0)),
                                 float(stereo.get("TZ", 0.0)), rvec, RESOLUTIONS[resolution], resolution=resolution)
    except (configparser.Error, KeyError, ValueError) as exc:
        raise ConfigError(f"{source} is not a ZED calibration file with [LEFT_CAM_{resolution}], "
                          f"[RIGHT_CAM_{resolution}] and [STEREO] Baseline: {exc}") from None


def _eye(parser: configparser.ConfigParser, section: str) -> EyeIntrinsics:
    s = parser[section]
    return EyeIntrinsics(float(s["fx"]), float(s["fy"]), float(s["cx"]), float(s["cy"]),
                         tuple(float(s.get(k, 0.0)) for k in DIST_KEYS))


def load_zed_conf(path: Path | str, resolution: str = "HD") -> StereoCalibration:
    """Read a calibration file; the serial number comes from its name ``SN<serial>.conf`` when it has one."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read ZED calibration file {path}: {exc.strerror} (on Linux the SDK keeps it "
                          f"in /usr/local/zed/settings/SN<serial>.conf)") from None
    calib = parse_zed_conf(text, resolution, str(path))
    serial = path.stem[2:] if path.stem.startswith("SN") else ""
    return StereoCalibration(**{**calib.__dict__, "serial": serial})


class Rectifier:
    """cv2.stereoRectify (zero disparity at infinity, alpha 0) and the remap tables of both eyes."""

    def __init__(self, calib: StereoCalibration) -> None:
        import cv2

        self.calib = calib
        k1, k2 = calib.left.matrix, calib.right.matrix
        d1, d2 = np.array(calib.left.dist), np.array(calib.right.dist)
        self.R1, self.R2, self.P1, self.P2, self.Q, _, _ = cv2.stereoRectify(
            k1, d1, k2, d2, calib.size, calib.rotation, calib.translation.reshape(3, 1),
            flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
        self.maps = [cv2.initUndistortRectifyMap(k, d, r, p, calib.size, cv2.CV_32FC1)
                     for k, d, r, p in ((k1, d1, self.R1, self.P1), (k2, d2, self.R2, self.P2))]

    @cached_property
    def focal_px(self) -> float:
        return float(self.P1[0, 0])

    @cached_property
    def baseline_mm(self) -> float:
        """Baseline of the rectified pair (mm): Z = focal_px * baseline_mm / disparity_px."""
        return float(-self.P2[0, 3] / self.P2[0, 0])

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import cv2

        return tuple(cv2.remap(img, mx, my, cv2.INTER_LINEAR) for img, (mx, my) in zip((left, right), self.maps))

    def to_rectified(self, points_px: np.ndarray) -> np.ndarray:
        """Raw left-image pixels (N, 2) -> rectified left-image pixels (N, 2)."""
        import cv2

        pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 1, 2)
        return cv2.undistortPoints(pts, self.calib.left.matrix, np.array(self.calib.left.dist),
                                   R=self.R1, P=self.P1, criteria=UNDISTORT_CRITERIA).reshape(-1, 2)

    def to_camera(self, rect_px: np.ndarray, disparity_px: np.ndarray) -> np.ndarray:
        """Rectified left pixels (N, 2) + disparities (N,) -> points (N, 3) mm in the raw left camera frame."""
        f, cx, cy = self.focal_px, self.P1[0, 2], self.P1[1, 2]
        z = f * self.baseline_mm / np.asarray(disparity_px, dtype=float)
        rect = np.column_stack([(rect_px[:, 0] - cx) * z / f, (rect_px[:, 1] - cy) * z / f, z])
        return rect @ self.R1  # R1 rotates raw-left into rectified-left coordinates: invert it
