"""Known ground truth of a simulated session: EmHT -> MTM transform, field distortion, latencies, PSM
coupling; written to ``calib/ground_truth.json`` so analyses can be checked against it.

Relation (positions in mm): MTM position of hand h at true time t =
    R @ p_T,h(t) + t_mm + f(p_T,h(t)),
p_T,h = midpoint of that hand's thumb and middle EmHT sensors (sensors 2+1 left, 3+4 right) in the
transmitter frame; an EmHT row stamped at host time T holds the pose at true time T - latency.
Distortion f (smooth, zero on the three planes through ``centre_mm``): with u = (p - centre) / wavelength,
    f_x = A_x sin(pi u_y) sin(pi u_z),  f_y = A_y sin(pi u_z) sin(pi u_x),  f_z = A_z sin(pi u_x) sin(pi u_y).
MTM orientation of hand h = R @ H_h, H_h the hand (gripper) frame; a sensor's frame is
H_h @ Rz(side * a) @ Rx(side * 90 deg) (a = half the grasp angle, side +1 / -1 for the two pads).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from midas_cli.geometry import matrices_from_angles

EMHT_TO_MTM_ANGLES_DEG = (160.0, 8.0, -5.0)  # azimuth, elevation, roll of R (Rz @ Ry @ Rx)
EMHT_TO_MTM_T_MM = (-250.0, 40.0, 320.0)
DISTORTION_CENTRE_MM = (300.0, 0.0, 150.0)
DISTORTION_WAVELENGTH_MM = 200.0
DISTORTION_SHAPE = (1.0, 0.75, 1.25)  # relative amplitudes of f_x, f_y, f_z (largest scaled to --distortion-mm)
PSM_SCALE = 0.4
PSM_ORIGIN_MM = (0.0, 0.0, -120.0)
GRASPER_OPEN_THRESHOLD_DEG = 35.0


@dataclass(frozen=True)
class Distortion:
    """The smooth non-linear field f (see module docstring); amplitude_mm (3,)."""

    amplitude_mm: np.ndarray
    centre_mm: np.ndarray
    wavelength_mm: float

    @classmethod
    def scaled(cls, peak_mm: float) -> "Distortion":
        shape = np.asarray(DISTORTION_SHAPE)
        return cls(shape / shape.max() * peak_mm, np.asarray(DISTORTION_CENTRE_MM), DISTORTION_WAVELENGTH_MM)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """f(p) (..., 3) mm for transmitter-frame points (..., 3) mm."""
        s = np.sin(np.pi * (points - self.centre_mm) / self.wavelength_mm)
        return self.amplitude_mm * np.stack([s[..., 1] * s[..., 2], s[..., 2] * s[..., 0], s[..., 0] * s[..., 1]], -1)

    def to_json(self) -> dict[str, Any]:
        return {"formula": "u = (p - centre_mm) / wavelength_mm; f = A * (sin(pi u_y) sin(pi u_z), "
                           "sin(pi u_z) sin(pi u_x), sin(pi u_x) sin(pi u_y))",
                "amplitude_mm": self.amplitude_mm.tolist(), "centre_mm": self.centre_mm.tolist(),
                "wavelength_mm": self.wavelength_mm}


@dataclass(frozen=True)
class GroundTruth:
    rotation: np.ndarray  # (3, 3) EmHT transmitter -> MTM
    translation_mm: np.ndarray  # (3,)
    distortion: Distortion
    emht_latency_ms: float

    @classmethod
    def build(cls, distortion_mm: float, latency_ms: float) -> "GroundTruth":
        rotation = matrices_from_angles(np.array([EMHT_TO_MTM_ANGLES_DEG]))[0]
        return cls(rotation, np.asarray(EMHT_TO_MTM_T_MM), Distortion.scaled(distortion_mm), latency_ms)

    def mtm_position(self, midpoints: np.ndarray) -> np.ndarray:
        """MTM positions (..., 3) mm from transmitter-frame hand midpoints (..., 3) mm."""
        return midpoints @ self.rotation.T + self.translation_mm + self.distortion(midpoints)

    def to_json(self, camera: tuple[np.ndarray, np.ndarray]) -> dict[str, Any]:
        """The calib/ground_truth.json document; ``camera`` = (R, t) with p_camera = R p_T + t."""
        cam_r, cam_t = camera
        hk_r = self.rotation @ cam_r.T
        return {
            "note": "simulated session: exact ground truth of the generator (midas simulate dataset)",
            "emht_to_mtm": {"R": self.rotation.tolist(), "t_mm": self.translation_mm.tolist(),
                            "angles_deg": {"azimuth": EMHT_TO_MTM_ANGLES_DEG[0], "elevation": EMHT_TO_MTM_ANGLES_DEG[1],
                                           "roll": EMHT_TO_MTM_ANGLES_DEG[2], "convention": "R = Rz(az) Ry(el) Rx(roll)"}},
            "mtm_hand_point": "midpoint of the thumb and middle sensors of that hand (left: sensors 2+1, right: 3+4)",
            "mtm_position": "R @ p + t_mm + f(p), p = hand point in the EmHT transmitter frame at the true time",
            "mtm_orientation": "R @ H, H = hand frame; sensor frame = H @ Rz(side*a) @ Rx(side*90deg), a = half grasp angle",
            "distortion": self.distortion.to_json(),
            "emht_latency_ms": self.emht_latency_ms,
            "emht_latency_meaning": "an emht row stamped at host time T holds the pose at true time T - latency",
            "handkp_to_mtm": {"R": hk_r.tolist(), "t_mm": (self.translation_mm - hk_r @ cam_t).tolist(),
                              "note": "p_mtm = R p_camera + t_mm + f(p_T) with p_T = camera_to_emht(p_camera); "
                                      "hand point = midpoint of thumb and middle keypoints; handkp latency 0",
                              "camera_from_emht": {"R": cam_r.tolist(), "t_mm": cam_t.tolist()}},
            "psm_from_mtm": {"scale": PSM_SCALE, "origin_mm": list(PSM_ORIGIN_MM),
                             "note": "psm position = scale * (mtm - mtm at the last clutch release) + psm at that "
                                     "release (origin_mm + scale * mtm at the start); frozen while clutch = 1; "
                                     "orientation and grasper angle equal the MTM's"},
            "grasper": {"open_threshold_deg": GRASPER_OPEN_THRESHOLD_DEG,
                        "angle": "grasper_deg = 2 * asin(d / (2 * 70 mm)), d = thumb-middle sensor distance (mm)"},
        }


def psm_positions(mtm: np.ndarray, clutch: np.ndarray) -> np.ndarray:
    """PSM positions (N, 3) from MTM positions (N, 3) and clutch (N,) bool (see ``psm_from_mtm``)."""
    psm = np.empty_like(mtm)
    offset = np.asarray(PSM_ORIGIN_MM)
    coupled_from = 0
    if clutch[0]:
        psm[:] = PSM_SCALE * mtm[0] + offset
    for i in np.flatnonzero(np.diff(clutch.astype(np.int8)) != 0) + 1:
        if clutch[i]:  # press: freeze from here
            psm[coupled_from:i] = PSM_SCALE * mtm[coupled_from:i] + offset
            psm[i:] = psm[i - 1] if i else offset
        else:  # release: re-couple at the frozen position
            offset = psm[i - 1] - PSM_SCALE * mtm[i]
            coupled_from = i
    if not clutch[-1]:
        psm[coupled_from:] = PSM_SCALE * mtm[coupled_from:] + offset
    return psm
