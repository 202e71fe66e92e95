"""A synthetic stereo camera with known geometry: renders side-by-side frames of textured planes.

The scene, in the left camera frame (mm): a fronto-parallel textured background plane at
``background_mm`` and fronto-parallel textured discs ("fingertip markers") centred on given 3-D points.
Every pixel of each eye is traced exactly: its ray through the eye's distortion model (cv2
undistortPoints of the pixel centre) and pose (the calibration's R, T) hits the planes, and the
texture (a band-limited sum of sinusoids, so sub-pixel shifts are rendered faithfully) is evaluated at
the hit point. Depth and keypoint geometry recovered from these images can therefore be checked
against ground truth. The background is rendered once; each frame only re-renders the markers' boxes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from midas_cli.devices.rgbd.calibration import UNDISTORT_CRITERIA, EyeIntrinsics, StereoCalibration

MARKER_RADIUS_MM = 9.0
RAY_GRID_PX = 8


def zed_mini_like_calibration(serial: str = "SIM0001") -> StereoCalibration:
    """A ZED-Mini-like 720p calibration (63 mm baseline) with slight distortion and misalignment."""
    left = EyeIntrinsics(700.2, 700.0, 641.3, 356.2, (-0.04, 0.01, 0.0002, -0.0001, 0.0))
    right = EyeIntrinsics(699.6, 699.5, 636.8, 361.9, (-0.035, 0.008, -0.0001, 0.0002, 0.0))
    return StereoCalibration(left, right, 63.0, 0.15, -0.2, (0.0008, 0.0035, -0.0006), (1280, 720), serial, "HD")


@dataclass(frozen=True)
class Texture:
    """A sum of sinusoids over plane coordinates (mm): grey level 128 +- ~90."""

    freqs: np.ndarray  # (K, 2) cycles per mm
    phases: np.ndarray  # (K,)
    amps: np.ndarray  # (K,)

    @classmethod
    def random(cls, seed: int, wavelength_mm: tuple[float, float], count: int = 10) -> "Texture":
        rng = np.random.default_rng(seed)
        wavelength = rng.uniform(*wavelength_mm, count)
        angle = rng.uniform(0, np.pi, count)
        freqs = np.column_stack([np.cos(angle), np.sin(angle)]) / wavelength[:, None]
        amps = rng.uniform(0.5, 1.0, count)
        return cls(freqs, rng.uniform(0, 2 * np.pi, count), 90 * amps / amps.sum() * 2.2)

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        phase = 2 * np.pi * (x[..., None] * self.freqs[:, 0] + y[..., None] * self.freqs[:, 1]) + self.phases
        return 128 + np.sum(self.amps * np.sin(phase), axis=-1)


class SyntheticStereoCamera:
    """Renders (H, 2W, 3) uint8 side-by-side BGR frames of a background plane and marker discs."""

    def __init__(self, calib: StereoCalibration, background_mm: float = 1300.0, seed: int = 0) -> None:
        self.calib = calib
        self.background_mm = background_mm
        self.background_texture = Texture.random(seed, (14.0, 60.0))
        self.marker_textures = [Texture.random(seed + 100 + i, (4.0, 9.0)) for i in range(8)]
        self.eyes = [self._rays(calib.left, np.eye(3), np.zeros(3)),
                     self._rays(calib.right, calib.rotation, calib.right_centre)]
        self.projections = [(calib.left, np.zeros(3), np.zeros(3)),
                            (calib.right, cv2_rvec(calib.rotation), calib.translation)]
        self.background = [self._plane(origin, dirs, background_mm, self.background_texture)
                           for origin, dirs in self.eyes]

    def _rays(self, eye: EyeIntrinsics, rotation: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(origin (3,), directions (H, W, 3)) of every pixel's ray, in the left camera frame."""
        import cv2

        w, h = self.calib.size
        step = RAY_GRID_PX  # rays are smooth in the pixel position: trace a coarse grid, interpolate
        gu, gv = np.meshgrid(np.arange(0, w + step, step, dtype=np.float64),
                             np.arange(0, h + step, step, dtype=np.float64))
        pix = np.stack([gu, gv], axis=-1).reshape(-1, 1, 2)
        coarse = cv2.undistortPoints(pix, eye.matrix, np.array(eye.dist), criteria=UNDISTORT_CRITERIA)
        coarse = coarse.reshape(gu.shape + (2,)).astype(np.float32)
        u, v = np.meshgrid(np.arange(w, dtype=np.float32) / step, np.arange(h, dtype=np.float32) / step)
        norm = np.stack([cv2.remap(np.ascontiguousarray(coarse[..., k]), u, v, cv2.INTER_LINEAR) for k in range(2)],
                        axis=-1).astype(np.float64)
        dirs_eye = np.concatenate([norm, np.ones((h, w, 1))], axis=-1)
        return centre, dirs_eye @ rotation  # eye -> left coordinates: R^T d, row-vector form d @ R

    @staticmethod
    def _plane(origin: np.ndarray, dirs: np.ndarray, z_mm: float, texture: Texture) -> np.ndarray:
        t = (z_mm - origin[2]) / dirs[..., 2]
        return np.clip(texture(origin[0] + t * dirs[..., 0], origin[1] + t * dirs[..., 1]), 0, 255).astype(np.uint8)

    def render(self, markers_mm: np.ndarray, radius_mm: float = MARKER_RADIUS_MM) -> np.ndarray:
        """Side-by-side BGR frame with a disc at each finite marker centre (N, 3) mm (NaN rows: no marker)."""
        eyes = []
        for (origin, dirs), background, projection in zip(self.eyes, self.background, self.projections):
            image = background.copy()
            depth = np.full(image.shape, np.inf)
            order = np.argsort(-np.nan_to_num(markers_mm[:, 2], nan=-1))  # far to near: nearer discs cover
            for i in order:
                box = _box(projection, markers_mm[i], radius_mm, image.shape)
                if box is not None:
                    self._disc(image, depth, origin, dirs, box, markers_mm[i], radius_mm, self.marker_textures[i % 8])
            eyes.append(image)
        grey = np.concatenate(eyes, axis=1)
        return np.repeat(grey[:, :, None], 3, axis=2)

    @staticmethod
    def _disc(image: np.ndarray, depth: np.ndarray, origin: np.ndarray, dirs: np.ndarray, box: tuple,
              centre: np.ndarray, radius: float, texture: Texture) -> None:
        (r0, r1), (c0, c1) = box
        d = dirs[r0:r1, c0:c1]
        t = (centre[2] - origin[2]) / d[..., 2]
        x, y = origin[0] + t * d[..., 0] - centre[0], origin[1] + t * d[..., 1] - centre[1]
        inside = (x * x + y * y <= radius * radius) & (centre[2] < depth[r0:r1, c0:c1])
        patch = np.clip(texture(x, y), 0, 255).astype(np.uint8)
        image[r0:r1, c0:c1][inside] = patch[inside]
        depth[r0:r1, c0:c1][inside] = centre[2]


def cv2_rvec(rotation: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(rotation)[0].ravel()


def _box(projection: tuple, centre: np.ndarray, radius: float, shape: tuple) -> tuple | None:
    """Pixel rows/columns of one eye that can see the disc (its projection + 3 px), or None if off-image."""
    import cv2

    eye, rvec, tvec = projection
    if not np.isfinite(centre).all() or centre[2] <= radius:
        return None
    px, _ = cv2.projectPoints(centre.reshape(1, 1, 3), rvec, tvec, eye.matrix, np.array(eye.dist))
    u, v = px.ravel()
    reach = eye.fx * radius / (centre[2] - radius) * 1.1 + 3
    h, w = shape
    r0, r1 = int(max(0, v - reach)), int(min(h, v + reach + 1))
    c0, c1 = int(max(0, u - reach)), int(min(w, u + reach + 1))
    return ((r0, r1), (c0, c1)) if r1 > r0 and c1 > c0 else None


def project_left(calib: StereoCalibration, points_mm: np.ndarray) -> np.ndarray:
    """Points (N, 3) mm in the left camera frame -> raw (distorted) left-image pixels (N, 2)."""
    import cv2

    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 1, 3)
    px, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), calib.left.matrix, np.array(calib.left.dist))
    return px.reshape(-1, 2)


def occluded(points_mm: np.ndarray, radius_mm: float = MARKER_RADIUS_MM, margin_mm: float = 3.0) -> np.ndarray:
    """(N,) bool: the left camera's ray to point i passes through a nearer marker disc j (or near its rim)."""
    hidden = np.zeros(len(points_mm), dtype=bool)
    for i, p in enumerate(points_mm):
        for j, q in enumerate(points_mm):
            if i == j or not (np.isfinite(p).all() and np.isfinite(q).all()) or q[2] >= p[2]:
                continue
            hit = p[:2] * q[2] / p[2]  # where the ray to p crosses the plane of disc j
            hidden[i] |= np.hypot(*(hit - q[:2])) < radius_mm + margin_mm
    return hidden
