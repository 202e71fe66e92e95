"""Deterministic model of a surgeon's hands and feet at a robot console: ``SurgeonMotion`` and its
tunables ``MotionConfig``.

The simulated devices (EmHT, HandKP, FPS), the trakSTAR, FPS and Raven emulators, the synthetic stereo
camera and the simulated datasets all sample this one model, so that their streams describe the same
surgeon and can be checked against known ground truth.

Clock: every ``t`` is seconds since the simulated device started (float64, >= 0, any order).

Determinism: every output is a pure function of ``(MotionConfig, t)``. Event schedules (reach targets,
grasp cycles, pedal presses, detection gaps) are drawn per fixed-length chunk of time from
``(seed, stream, chunk index)`` only, and generated lazily up to the largest ``t`` seen; per-sample noise
is a counter-based hash of ``(seed, stream, t rounded to microseconds)``. Evaluating a time range in one
call or in many small batches therefore gives bit-identical values.

Frames:

* transmitter frame (EmHT): trakSTAR convention, mm. x = depth (away from the transmitter),
  y = lateral (surgeon's right positive), z = vertical (down positive).
* camera frame (HandKP): OpenCV/ZED convention, mm. x = image right, y = image down, z = optical axis.
  ``SurgeonMotion.camera_from_transmitter()`` gives the fixed rigid transform.

Hand model: :mod:`midas_cli.synthetic.hands` (clutch presses, pedal index ``CLUTCH_PEDAL``, move the
hands back near the workspace middle). Foot model: :mod:`midas_cli.synthetic.feet`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from midas_cli.geometry import angles_from_matrices, apply_rigid, matrices_from_angles
from midas_cli.synthetic.feet import DEFAULT_PEDAL_PROFILES, N_PEDALS, FootModel
from midas_cli.synthetic.hands import HAND_SENSORS, HandModel, pad_rotation
from midas_cli.synthetic.noise import hash_normal, hash_uniform, microseconds, seeded_rng
from midas_cli.synthetic.schedule import CHUNK_MARGIN_S, EventProfile, IntervalSchedule, renewal_events

KEYPOINT_NAMES = ("thumb", "middle")

# stream ids: each random schedule / noise source draws from its own (seed, stream, ...) key
_STREAM_OCCLUSION = 50
_STREAM_KEYPOINT_NOISE = 100
_STREAM_KEYPOINT_MISS = 120


@dataclass(frozen=True)
class MotionConfig:
    """Tunables of the surgeon model. Lengths in mm, times in s, angles in degrees, forces in N.

    Half-open fingertips in the neutral wrist pose sit at ``workspace_centre_mm`` +/- hand_separation_mm / 2
    laterally; focus, reaches and the grip opening move them about +/-100 mm laterally and +/-50 mm in
    depth/height (99 % of samples; ~300 mm from the transmitter). Changing ``chunk_s`` changes every schedule.
    """

    seed: int = 0
    n_pedals: int = N_PEDALS
    chunk_s: float = 60.0
    # hands: position
    workspace_centre_mm: tuple[float, float, float] = (300.0, 0.0, 150.0)
    hand_separation_mm: float = 90.0
    focus_half_extent_mm: tuple[float, float, float] = (15.0, 12.0, 15.0)
    focus_hold_s: tuple[float, float] = (0.5, 3.0)
    reach_half_extent_mm: tuple[float, float, float] = (22.0, 20.0, 22.0)
    reach_hold_s: tuple[float, float] = (0.3, 2.0)
    reach_base_s: float = 0.3
    reach_speed_mm_s: float = 150.0
    fine_motion_mm: float = 1.5
    fine_rotation_deg: float = 3.0
    fine_interval_s: tuple[float, float] = (0.3, 1.0)
    tremor_mm: float = 0.12
    tremor_hz: tuple[float, float] = (8.0, 12.0)
    # hands: orientation (azimuth/yaw, elevation/pitch, roll)
    wrist_base_deg: tuple[float, float, float] = (10.0, -20.0, 0.0)
    wrist_half_range_deg: tuple[float, float, float] = (15.0, 15.0, 30.0)
    # hands: grasping
    grip_lever_mm: float = 70.0
    aperture_open_mm: tuple[float, float] = (60.0, 80.0)
    aperture_closed_mm: tuple[float, float] = (17.0, 25.0)
    aperture_wobble_mm: float = 0.7
    grasp_open_hold_s: tuple[float, float] = (0.8, 3.0)
    grasp_closed_hold_s: tuple[float, float] = (0.3, 2.0)
    grasp_transition_s: tuple[float, float] = (0.2, 0.45)
    # feet and FSR pedal board
    pedal_profiles: tuple[EventProfile | None, ...] = DEFAULT_PEDAL_PROFILES
    pedal_force_n: tuple[float, float] = (2.5, 40.0)  # peak foot force per press, log-uniform
    press_rise_s: tuple[float, float] = (0.02, 0.06)
    bounce_window_s: tuple[float, float] = (0.003, 0.010)
    fsr_series_ohm: float = 3300.0
    fsr_ohm_at_1n: float = 6000.0
    fsr_exponent: float = 0.75
    fsr_rest_ohm: tuple[float, float] = (2e5, 2e6)
    resting_foot_max_n: float = 0.02
    adc_noise_counts: float = 1.5
    # depth camera hand keypoints
    camera_distance_mm: float = 600.0
    camera_tilt_deg: float = 15.0
    camera_yaw_deg: float = 4.0
    keypoint_noise_mm: tuple[float, float, float] = (1.5, 1.5, 2.5)
    keypoint_miss_probability: float = 0.015
    occlusion_profile: EventProfile = EventProfile(10.0, 30.0, 0.2, 2.0)

    def __post_init__(self) -> None:
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if len(self.pedal_profiles) != N_PEDALS:
            raise ValueError(f"pedal_profiles needs one entry (or None) per FPS channel, {N_PEDALS}")
        if not 1 <= self.n_pedals <= N_PEDALS:
            raise ValueError(f"n_pedals must be in 1..{N_PEDALS}, got {self.n_pedals}")
        if self.aperture_open_mm[1] + self.aperture_wobble_mm * 2 >= 2 * self.grip_lever_mm:
            raise ValueError("aperture_open_mm must stay below twice grip_lever_mm")
        if self.chunk_s <= 4 * CHUNK_MARGIN_S:
            raise ValueError(f"chunk_s must exceed {4 * CHUNK_MARGIN_S} s, got {self.chunk_s}")


class SurgeonMotion:
    """Hands and feet of one simulated surgeon; every method takes t (N,) = seconds since device start.

    ``hands`` (:class:`~midas_cli.synthetic.hands.HandModel`) and ``feet``
    (:class:`~midas_cli.synthetic.feet.FootModel`) are the two halves; the clutch presses of the feet
    steer the hands.
    """

    def __init__(self, config: MotionConfig = MotionConfig()) -> None:
        self.config = config
        self.feet = FootModel(config)
        self.hands = HandModel(config, self.feet.clutch_intervals)
        self._occlusions = [
            IntervalSchedule(config.chunk_s, lambda k, h=hand: self._occlusion_chunk(h, k)) for hand in range(2)
        ]

    def sensor_poses(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Poses of the 4 trakSTAR sensors (order ``SENSOR_NAMES``) in the transmitter frame.

        Returns positions (N, 4, 3) in mm and orientations (N, 4, 3) as azimuth, elevation, roll in
        degrees (azimuth and roll in [-180, 180), elevation in [-90, 90]). Noise-free apart from the
        physiological tremor: the device simulator adds measurement noise.
        """
        t = _as_times(t)
        positions, angles = np.empty((t.size, 4, 3)), np.empty((t.size, 4, 3))
        for sensor, state, side in self.hands.grip_pads(t):
            positions[:, sensor] = self.hands.pad_position(state, side)
            angles[:, sensor] = angles_from_matrices(pad_rotation(state, side), wrap=True)
        return positions, angles

    def grasper_aperture(self, t: np.ndarray) -> np.ndarray:
        """Ground-truth thumb-middle sensor distance (N, 2) in mm for the (left, right) hand."""
        t = _as_times(t)
        return np.column_stack([self.hands.aperture(t, hand) for hand in range(2)])

    def hand_keypoints(self, t: np.ndarray) -> np.ndarray:
        """Detected fingertips (N, 2, 2, 3): hand (``HAND_NAMES``) x keypoint (``KEYPOINT_NAMES``) x xyz, mm.

        In the camera frame (see ``camera_from_transmitter``), with ~3 mm detection noise; NaN for a
        whole hand where the detector misses it (isolated frames and occlusion runs).
        """
        t = _as_times(t)
        rotation, translation = self.camera_from_transmitter()
        sensors = self.hands.sensor_positions(t)
        keypoints = apply_rigid(rotation, translation, sensors[:, np.array(HAND_SENSORS)])
        keypoints += self._keypoint_noise(t)
        for hand in range(2):
            keypoints[self._keypoint_missed(t, hand), hand] = np.nan
        return keypoints

    def pedal_pressed(self, t: np.ndarray) -> np.ndarray:
        """Ground-truth press state (N, n_pedals) bool (True while the foot holds the pedal down)."""
        return self.feet.pressed(_as_times(t))

    def pedal_adc(self, t: np.ndarray) -> np.ndarray:
        """FSR divider readings (N, n_pedals) as 10-bit ADC counts 0..1023 (int32), Vcc = 5 V.

        Unpressed ~0-60 counts (mounting preload, resting foot, noise); pressed ~500-950 by force, with a
        few ms of contact bounce at press onset and release.
        """
        return self.feet.adc(_as_times(t))

    def camera_from_transmitter(self) -> tuple[np.ndarray, np.ndarray]:
        """Rigid transform (R (3, 3), t (3,) mm) with p_camera = R @ p_transmitter + t.

        The camera sits ``camera_distance_mm`` from the workspace centre along its optical axis, looking
        down (tilted by ``camera_tilt_deg``, turned by ``camera_yaw_deg``) at the centre.
        """
        cfg = self.config
        looking_down = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # columns: camera axes
        yaw = matrices_from_angles(np.array([[cfg.camera_yaw_deg, 0.0, 0.0]]))[0]
        tilt = matrices_from_angles(np.array([[0.0, 0.0, cfg.camera_tilt_deg]]))[0]
        axes = yaw @ looking_down @ tilt
        position = np.asarray(cfg.workspace_centre_mm) - cfg.camera_distance_mm * axes[:, 2]
        return axes.T, -axes.T @ position

    def _keypoint_noise(self, t: np.ndarray) -> np.ndarray:
        """Detection noise (N, 2, 2, 3) mm in the camera frame (per-axis sigma ``keypoint_noise_mm``)."""
        t_us = microseconds(t)
        noise = np.empty((t.size, 2, 2, 3))
        for index in np.ndindex(2, 2, 3):
            stream = _STREAM_KEYPOINT_NOISE + int(np.ravel_multi_index(index, (2, 2, 3)))
            noise[:, index[0], index[1], index[2]] = hash_normal(self.config.seed, stream, t_us)
        return noise * np.asarray(self.config.keypoint_noise_mm)

    def _keypoint_missed(self, t: np.ndarray, hand: int) -> np.ndarray:
        """(N,) bool: the detector misses this hand (isolated frame or occlusion run)."""
        isolated = hash_uniform(self.config.seed, _STREAM_KEYPOINT_MISS + hand, microseconds(t))
        return (isolated < self.config.keypoint_miss_probability) | self._occlusions[hand].lookup(t)[1]

    def _occlusion_chunk(self, hand: int, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(starts, ends) s of a hand's occlusion runs in chunk k."""
        cfg = self.config
        rng = seeded_rng(cfg.seed, _STREAM_OCCLUSION, hand, k)
        return renewal_events(rng, cfg.occlusion_profile, k * cfg.chunk_s, (k + 1) * cfg.chunk_s)


def _as_times(t: np.ndarray) -> np.ndarray:
    """Validated sample times: 1-D float64 array of finite values >= 0 (s since device start)."""
    times = np.atleast_1d(np.asarray(t, dtype=np.float64))
    if times.ndim != 1:
        raise ValueError(f"t must be 1-D, got shape {times.shape}")
    if times.size and not (np.isfinite(times).all() and times.min() >= 0.0):
        raise ValueError("t must be finite and >= 0 (seconds since the simulated device started)")
    return times
