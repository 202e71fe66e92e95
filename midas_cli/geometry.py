"""Geometry: rotations, quaternions and rigid transforms (pure numpy), the one home for this maths.

The ground floor: imports nothing from midas but its error types, and is used by the devices and
emulators (trakSTAR angles, Raven quaternions), the simulated surgeon and dataset, and the analysis
(calibration fits, alignment, evaluation).

Angle convention everywhere (trakSTAR's, also used for robot orientations): R = Rz(a) @ Ry(e) @ Rx(r)
with a = azimuth = yaw, e = elevation = pitch, r = roll, in degrees. Quaternions are (x, y, z, w),
scalar last, as the robot streams store them.
"""

from __future__ import annotations

import numpy as np

from midas_cli.errors import SessionError


def fit_similarity(source: np.ndarray, target: np.ndarray, with_scale: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares ``target ~ s R source + t`` (Kabsch; Umeyama when ``with_scale``).

    source, target: (N, 3) paired points (rows with NaN are ignored). Returns R (3, 3) proper rotation,
    t (3,) and s (1.0 unless ``with_scale``).
    """
    ok = np.isfinite(source).all(axis=1) & np.isfinite(target).all(axis=1)
    src, dst = source[ok], target[ok]
    if len(src) < 3:
        raise SessionError(f"a rigid fit needs at least 3 paired points, got {len(src)}")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)  # (3, 3)
    u, sing, vt = np.linalg.svd(cov)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rotation = u @ d @ vt
    scale = float(np.trace(np.diag(sing) @ d) / xs.var(axis=0).sum()) if with_scale else 1.0
    return rotation, mu_d - scale * rotation @ mu_s, scale


def apply_similarity(rotation: np.ndarray, translation: np.ndarray, scale: float, points: np.ndarray) -> np.ndarray:
    """``s R p + t`` for points (N, 3)."""
    return scale * points @ rotation.T + translation


def apply_rigid(rotation: np.ndarray, translation: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``R p + t`` for points (..., 3), summed column by column in a fixed order (no BLAS: the same
    bits on every machine, which the simulator's byte-identical sessions rely on)."""
    x, y, z = points[..., 0:1], points[..., 1:2], points[..., 2:3]
    return x * rotation[:, 0] + y * rotation[:, 1] + z * rotation[:, 2] + translation


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (degrees) of the rotation taking a (3, 3) to b (3, 3)."""
    cos = (np.trace(a.T @ b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def matrices_from_angles(angles_deg: np.ndarray) -> np.ndarray:
    """(N, 3) yaw (azimuth), pitch (elevation), roll in degrees -> (N, 3, 3) = Rz @ Ry @ Rx."""
    yaw, pitch, roll = np.radians(np.asarray(angles_deg, dtype=float)).T
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    entries = [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr,
               sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr,
               -sp, cp * sr, cp * cr]
    return np.stack(entries, axis=-1).reshape(-1, 3, 3)


def angles_from_matrices(rotations: np.ndarray, wrap: bool = False) -> np.ndarray:
    """(N, 3, 3) -> (N, 3) yaw, pitch, roll in degrees (inverse of ``matrices_from_angles``); yaw and
    roll in [-180, 180], or [-180, 180) with ``wrap`` (the trakSTAR's own range)."""
    yaw = np.arctan2(rotations[:, 1, 0], rotations[:, 0, 0])
    pitch = np.arcsin(np.clip(-rotations[:, 2, 0], -1.0, 1.0))
    roll = np.arctan2(rotations[:, 2, 1], rotations[:, 2, 2])
    degrees = np.degrees(np.column_stack([yaw, pitch, roll]))
    if wrap:
        degrees = np.column_stack([wrap_degrees(degrees[:, 0]), degrees[:, 1], wrap_degrees(degrees[:, 2])])
    return degrees


def wrap_degrees(angle: np.ndarray) -> np.ndarray:
    """Angles in degrees wrapped into [-180, 180)."""
    wrapped = np.mod(angle + 180.0, 360.0) - 180.0
    return np.where(wrapped >= 180.0, wrapped - 360.0, wrapped)


def matrices_from_quaternions(quat_xyzw: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (x, y, z, w), normalised here -> (N, 3, 3); NaN rows stay NaN."""
    q = np.asarray(quat_xyzw, dtype=float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    entries = [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
               2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
               2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]
    return np.stack(entries, axis=-1).reshape(-1, 3, 3)


def quaternions_from_matrices(rotations: np.ndarray) -> np.ndarray:
    """(N, 3, 3) -> (N, 4) unit quaternions (x, y, z, w) with w >= 0 (normalised: a rotation matrix
    that is a few ulps off orthonormal still gives a unit quaternion)."""
    m = rotations
    w = np.sqrt(np.clip(1 + m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2], 0, None)) / 2
    x = np.sqrt(np.clip(1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], 0, None)) / 2
    y = np.sqrt(np.clip(1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2], 0, None)) / 2
    z = np.sqrt(np.clip(1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2], 0, None)) / 2
    x = np.copysign(x, m[:, 2, 1] - m[:, 1, 2])
    y = np.copysign(y, m[:, 0, 2] - m[:, 2, 0])
    z = np.copysign(z, m[:, 1, 0] - m[:, 0, 1])
    q = np.column_stack([x, y, z, w])
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def rotation_vectors_from_matrices(rotations: np.ndarray) -> np.ndarray:
    """(N, 3, 3) -> (N, 3) rotation vectors (axis x angle, radians, angle in [0, pi]), the log map;
    exact near the identity (first order in the quaternion's vector part); NaN rows stay NaN."""
    with np.errstate(invalid="ignore", divide="ignore"):
        q = quaternions_from_matrices(rotations)
        v, w = q[:, :3], q[:, 3]
        norm = np.linalg.norm(v, axis=1)
        small = norm < 1e-9
        scale = np.where(small, 2.0 / np.where(small, w, 1.0), 2.0 * np.arctan2(norm, w) / np.where(small, 1.0, norm))
    return v * scale[:, None]


def angular_velocities(rotations: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """(N, 3, 3) orientations sampled at ``times_s`` (N,) -> (N, 3) angular velocity (rad/s) in the
    frame the rotations are expressed in (the base frame): central differences like ``np.gradient``,
    the rotation vector of R(t+1) R(t-1)^T over the time between them; one-sided at the ends."""
    n = len(rotations)
    if n < 2:
        return np.zeros((n, 3))
    before, after = np.r_[0, np.arange(n - 1)], np.r_[np.arange(1, n), n - 1]
    relative = rotations[after] @ np.swapaxes(rotations[before], 1, 2)  # (N, 3, 3)
    return rotation_vectors_from_matrices(relative) / (times_s[after] - times_s[before])[:, None]


def quaternions_from_angles(angles_deg: np.ndarray) -> np.ndarray:
    """(N, 3) azimuth, elevation, roll (Z, Y, X Euler, degrees) -> (N, 4) unit quaternions (x, y, z, w),
    straight from the half angles (the same rotation as ``matrices_from_angles``)."""
    half = np.radians(angles_deg) / 2
    cz, sz = np.cos(half[:, 0]), np.sin(half[:, 0])
    cy, sy = np.cos(half[:, 1]), np.sin(half[:, 1])
    cx, sx = np.cos(half[:, 2]), np.sin(half[:, 2])
    return np.column_stack([sx * cy * cz - cx * sy * sz, cx * sy * cz + sx * cy * sz,
                            cx * cy * sz - sx * sy * cz, cx * cy * cz + sx * sy * sz])


def mean_rotation(rotations: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations (N, 3, 3) (NaN rows ignored), projected onto SO(3)."""
    ok = np.isfinite(rotations).all(axis=(1, 2))
    if not ok.any():
        raise SessionError("no valid orientation samples to average")
    u, _, vt = np.linalg.svd(rotations[ok].sum(axis=0))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    return u @ d @ vt


def unwrap_deg(angles: np.ndarray, reference: np.ndarray | None = None) -> np.ndarray:
    """Unwrap an angle trajectory (N,) in degrees across +/-180 jumps (NaN kept in place); with
    ``reference``, shifted by whole turns so its median lies within 180 deg of the reference's."""
    out = np.array(angles, dtype=float)
    ok = np.isfinite(out)
    out[ok] = np.degrees(np.unwrap(np.radians(out[ok])))
    if reference is not None and ok.any() and np.isfinite(reference).any():
        out -= 360.0 * np.round((np.nanmedian(out) - np.nanmedian(reference)) / 360.0)
    return out
