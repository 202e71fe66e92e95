"""Deterministic model of a surgeon's hands and feet at a robot console.

The simulated devices (EmHT, HandKP, FPS) and the trakSTAR emulator all sample this one model, so that
their streams describe the same surgeon and can be checked against known ground truth.

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

Hand model: each hand holds a master-controller grip, a hinge ("grip point") with two levers of
``grip_lever_mm``; the thumb and middle-finger trakSTAR sensors sit on the lever pads. The grip point is
the sum of a shared, slowly shifting bimanual focus, per-hand minimum-jerk reaches between random targets
with holds (position and wrist angles together), small fine-manipulation movements and 8-12 Hz tremor.
During each clutch press (pedal index ``CLUTCH_PEDAL``) the focus and both hands move back near the
workspace middle. The grip opens and closes in grasp cycles.

Foot model: per pedal, a renewal process of presses; force -> FSR resistance (power law) -> voltage
divider ``Vout = R / (R + R_fsr) * Vcc`` (Vcc = 5 V) -> 10-bit ADC counts, with contact bounce at the
edges of each press and a lightly resting foot between presses.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np

from midas_cli.geometry import angles_from_matrices, apply_rigid, matrices_from_angles

log = logging.getLogger(__name__)

SENSOR_NAMES = ("left_middle", "left_thumb", "right_thumb", "right_middle")  # trakSTAR sensors 1..4
N_PEDALS = 9
CLUTCH_PEDAL = 4  # 0-based FPS channel; "Pedal 5 = Clutch" in the paper's mapping
CAMERA_PEDAL = 5
HAND_NAMES = ("left", "right")
KEYPOINT_NAMES = ("thumb", "middle")

_HAND_SENSORS = ((1, 0), (2, 3))  # per hand: (thumb, middle) indices into SENSOR_NAMES
_THUMB_SIDE = (1.0, -1.0)  # per hand: hand-frame y side of the thumb pad (medial, towards the midline)
_HAND_LATERAL_SIGN = (-1.0, 1.0)
_CHUNK_MARGIN_S = 1.0  # events (presses, occlusions) start and end at least this far from chunk edges
_MIN_APERTURE_END_GAP_S = 0.5
_FOCUS_SHIFT_BASE_S = 0.8  # duration of a focus shift: base + distance / speed
_FOCUS_SHIFT_SPEED_MM_S = 40.0
_RECENTRED_FRACTION = 0.15  # after a clutch press, offsets are this fraction of a random target

# stream ids: each random schedule / noise source draws from its own (seed, stream, ...) key
_STREAM_FOCUS = 1
_STREAM_FOCUS_BOUNDARY = 2
_STREAM_REACH = 10
_STREAM_REACH_BOUNDARY = 12
_STREAM_GRASP = 20
_STREAM_GRASP_BOUNDARY = 22
_STREAM_PEDAL = 30
_STREAM_OCCLUSION = 50
_STREAM_HAND_STATIC = 60
_STREAM_FINE = 62
_STREAM_FINE_BOUNDARY = 64
_STREAM_PEDAL_STATIC = 70
_STREAM_KEYPOINT_NOISE = 100
_STREAM_KEYPOINT_MISS = 120
_STREAM_ADC_NOISE = 140

# columns of the per-press parameter table
_PEAK_N, _ON_BOUNCES, _OFF_BOUNCES, _ON_WINDOW_S, _OFF_WINDOW_S, _RISE_S, _FALL_S, _WOBBLE_PHASE = range(8)
_CONTACT_FORCE_FRACTION = 0.3  # foot impact: force jumps to at least this fraction of the peak
_PRESS_WOBBLE = (0.06, 1.3)  # relative amplitude, Hz of foot-force variation while holding a pedal
_BOUNCE_COUNT_PROBABILITIES = (0.2, 0.4, 0.3, 0.1)  # P(0, 1, 2, 3 contact gaps) at a press edge


@dataclass(frozen=True)
class EventProfile:
    """Renewal process of timed events (pedal presses, detector occlusions), seconds.

    The gap from one event's end to the next event's start is ~ U(gap_min_s, gap_max_s); the first event
    of a chunk starts U(0, gap_max_s) after the chunk start; durations are ~ U(duration_min_s,
    duration_max_s). Events never span a chunk boundary.
    """

    gap_min_s: float
    gap_max_s: float
    duration_min_s: float
    duration_max_s: float


DEFAULT_PEDAL_PROFILES: tuple[EventProfile | None, ...] = (
    EventProfile(300.0, 900.0, 0.3, 1.0),  # Pedal 1: secondary energy (L), rare
    EventProfile(20.0, 60.0, 0.2, 1.0),  # Pedal 2: secondary energy (R), short presses
    EventProfile(300.0, 900.0, 0.3, 1.0),  # Pedal 3: primary energy (L), rare
    EventProfile(6.0, 25.0, 0.3, 1.5),  # Pedal 4: primary energy (R), short presses
    EventProfile(20.0, 40.0, 0.5, 2.0),  # Pedal 5: clutch
    EventProfile(30.0, 90.0, 1.0, 4.0),  # Pedal 6: camera
    EventProfile(600.0, 1800.0, 0.2, 0.6),  # Pedal 7: arm swap, rare
    None,  # Pedal 8: unmapped
    None,  # Pedal 9: unmapped
)


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
        if self.chunk_s <= 4 * _CHUNK_MARGIN_S:
            raise ValueError(f"chunk_s must exceed {4 * _CHUNK_MARGIN_S} s, got {self.chunk_s}")


# ---------------------------------------------------------------------------------------------------
# deterministic randomness


def _rng(seed: int, *key: int) -> np.random.Generator:
    """A generator that depends only on (seed, key...)."""
    return np.random.default_rng(np.random.SeedSequence([seed, *key]))


_GOLDEN_GAMMA = np.uint64(0x9E3779B97F4A7C15)


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser: a bijective avalanche hash of uint64 values (wrapping arithmetic)."""
    with np.errstate(over="ignore"):
        z = x + _GOLDEN_GAMMA
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def _hash_uniform(seed: int, stream: int, t_us: np.ndarray) -> np.ndarray:
    """Uniform (0, 1) per sample, a pure function of (seed, stream, t in integer microseconds)."""
    key = _splitmix64(np.array([(seed * 0x100000001B3 + stream) % 2**64], dtype=np.uint64))
    z = _splitmix64(t_us ^ _splitmix64(key))
    return ((z >> np.uint64(11)).astype(np.float64) + 0.5) * 2.0**-53


def _hash_normal(seed: int, stream: int, t_us: np.ndarray) -> np.ndarray:
    """Standard normal per sample (Box-Muller over two hashed uniforms)."""
    radius = np.sqrt(-2.0 * np.log(_hash_uniform(seed, 2 * stream, t_us)))
    return radius * np.cos(2.0 * np.pi * _hash_uniform(seed, 2 * stream + 1, t_us))


def _microseconds(t: np.ndarray) -> np.ndarray:
    """Sample times (s) as integer microseconds, the key of every per-sample noise value."""
    return np.rint(t * 1e6).astype(np.uint64)


# ---------------------------------------------------------------------------------------------------
# chunked schedules


def _minimum_jerk(s: np.ndarray) -> np.ndarray:
    """Minimum-jerk profile 10 s^3 - 15 s^4 + 6 s^5 for s in [0, 1] (zero velocity/acceleration at ends)."""
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s))


class _ChunkedSchedule:
    """Arrays generated per time chunk and concatenated; chunk k comes from ``make_chunk(k)`` alone."""

    def __init__(self, chunk_s: float, make_chunk: Callable[[int], tuple[np.ndarray, ...]]) -> None:
        self._chunk_s = chunk_s
        self._make_chunk = make_chunk
        self._chunks: list[tuple[np.ndarray, ...]] = []
        self._fields: tuple[np.ndarray, ...] = ()

    def fields_covering(self, t: np.ndarray) -> tuple[np.ndarray, ...]:
        """The concatenated arrays of chunks 0 .. (chunk of max t) + 1."""
        last_chunk = int(t.max() // self._chunk_s) + 1 if t.size else 1
        if len(self._chunks) <= last_chunk:
            log.debug("extending schedule to chunk %d", last_chunk)
            while len(self._chunks) <= last_chunk:
                self._chunks.append(self._make_chunk(len(self._chunks)))
            self._fields = tuple(np.concatenate(parts) for parts in zip(*self._chunks))
        return self._fields


class _KnotCurve(_ChunkedSchedule):
    """Piecewise minimum-jerk curve through knots (times (K,), values (K, D)).

    ``make_chunk(k)`` returns the knots in [k * chunk_s, (k + 1) * chunk_s), the first exactly at
    k * chunk_s; the last segment of a chunk runs to the first knot of the next chunk.
    """

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """Curve values (N, D) at t (N,)."""
        times, values = self.fields_covering(t)
        start = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
        span = times[start + 1] - times[start]
        progress = _minimum_jerk(np.clip((t - times[start]) / span, 0.0, 1.0))
        return values[start] + (values[start + 1] - values[start]) * progress[:, None]


class _IntervalSchedule(_ChunkedSchedule):
    """Non-overlapping intervals (starts (M,), ends (M,), params (M, P)), each inside one chunk."""

    def lookup(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(index (N,) of the interval at or before t, inside (N,) bool: start <= t < end)."""
        starts, ends = self.fields_covering(t)[:2]
        if starts.size == 0:
            return np.zeros(t.shape, dtype=np.intp), np.zeros(t.shape, dtype=bool)
        index = np.searchsorted(starts, t, side="right") - 1
        inside = (index >= 0) & (t < ends[np.maximum(index, 0)])
        return np.maximum(index, 0), inside


def _renewal_events(
    rng: np.random.Generator, profile: EventProfile | None, t0: float, t1: float
) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends) in s of a renewal process inside [t0 + margin, t1 - margin]."""
    if profile is None:
        return np.empty(0), np.empty(0)
    count = int((t1 - t0) / (profile.gap_min_s + profile.duration_min_s)) + 2
    first_gap = rng.uniform(0.0, profile.gap_max_s, 1)
    gaps = np.concatenate([first_gap, rng.uniform(profile.gap_min_s, profile.gap_max_s, count - 1)])
    durations = rng.uniform(profile.duration_min_s, profile.duration_max_s, count)
    starts = t0 + _CHUNK_MARGIN_S + np.cumsum(gaps) + np.concatenate([[0.0], np.cumsum(durations[:-1])])
    ends = starts + durations
    keep = ends <= t1 - _CHUNK_MARGIN_S
    return starts[keep], ends[keep]


def _focus_shift_duration(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Duration (M,) s of slow shifts of the bimanual focus a -> b (M, 3) mm."""
    return _FOCUS_SHIFT_BASE_S + np.linalg.norm(b - a, axis=1) / _FOCUS_SHIFT_SPEED_MM_S


def _reach_hold_knots(
    rng: np.random.Generator,
    span: tuple[float, float],
    endpoints: tuple[np.ndarray, np.ndarray],
    targets: np.ndarray,
    reach_duration: Callable[[np.ndarray, np.ndarray], np.ndarray],
    hold_s: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """Knots of hold-then-reach cycles from (t0, v0) through ``targets`` and a final reach onto (t1, v1).

    targets (M, D) must be enough to overrun the span; ``reach_duration(a, b)`` gives the duration (s,
    shape (M,)) of moves a -> b (both (M, D)). Returns times (K,) and values (K, D), both ends included.
    """
    (t0, t1), (v0, v1) = span, endpoints
    path = np.vstack([v0, targets])
    reach = reach_duration(path[:-1], path[1:])
    arrive = t0 + np.cumsum(rng.uniform(*hold_s, len(reach)) + reach)
    depart = arrive - reach
    fits = arrive + hold_s[0] + reach_duration(path[1:], np.broadcast_to(v1, targets.shape)) <= t1
    n = len(fits) if fits.all() else int(np.argmin(fits))
    times = [np.array([t0]), np.column_stack([depart[:n], arrive[:n]]).ravel()]
    values = [v0[None], np.stack([path[:n], path[1 : n + 1]], axis=1).reshape(2 * n, path.shape[1])]
    last_time, last_value = (arrive[n - 1] if n else t0), path[n]
    final_depart = t1 - reach_duration(last_value[None], v1[None])[0]
    if final_depart > last_time:
        times.append(np.array([final_depart]))
        values.append(last_value[None])
    times.append(np.array([t1]))
    values.append(v1[None])
    return np.concatenate(times), np.concatenate(values)


@dataclass(frozen=True)
class _ReachStyle:
    """How a hold-and-reach process moves: random targets, move durations (s), hold durations (s)."""

    draw_targets: Callable[[np.random.Generator, int], np.ndarray]  # (rng, count) -> (count, D)
    duration: Callable[[np.ndarray, np.ndarray], np.ndarray]  # (from (M, D), to (M, D)) -> (M,) s
    hold_s: tuple[float, float]
    shortest_move_s: float

    def knots(
        self, rng: np.random.Generator, span: tuple[float, float], endpoints: tuple[np.ndarray, np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Knots (times (K,), values (K, D)) of holds and reaches filling ``span`` between ``endpoints``."""
        count = int((span[1] - span[0]) / (self.hold_s[0] + self.shortest_move_s)) + 2
        return _reach_hold_knots(rng, span, endpoints, self.draw_targets(rng, count), self.duration, self.hold_s)


@dataclass(frozen=True)
class _SinusoidBank:
    """Sum of sinusoids per dimension: frequencies_hz, amplitudes, phases_rad all (D, C)."""

    frequencies_hz: np.ndarray
    amplitudes: np.ndarray
    phases_rad: np.ndarray

    @classmethod
    def draw(cls, rng: np.random.Generator, hz: tuple[float, float], amplitudes: np.ndarray) -> _SinusoidBank:
        """Random frequencies in ``hz`` and random phases for the given amplitudes (D, C)."""
        frequencies = rng.uniform(hz[0], hz[1], amplitudes.shape)
        return cls(frequencies, amplitudes, rng.uniform(0.0, 2.0 * np.pi, amplitudes.shape))

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """Values (N, D) at t (N,) s."""
        angle = 2.0 * np.pi * self.frequencies_hz * t[:, None, None] + self.phases_rad
        return (self.amplitudes * np.sin(angle)).sum(axis=-1)


@dataclass(frozen=True)
class _HandState:
    """One hand at N times: grip point (N, 3) mm, hand rotation (N, 3, 3), grip half-opening (N,) rad."""

    grip_point: np.ndarray
    rotation: np.ndarray
    half_angle: np.ndarray


def _pad_rotation(state: _HandState, side: float) -> np.ndarray:
    """Sensor rotations (N, 3, 3) on the pad at ``side`` (+1 / -1 along hand-frame y).

    hand rotation @ Rz(side * half_angle) @ Rx(side * 90 deg): sensor x runs along the lever, sensor z is
    the pad normal pointing at the other pad.
    """
    cos, sin = np.cos(state.half_angle)[:, None], side * np.sin(state.half_angle)[:, None]
    hand_x, hand_y, hand_z = state.rotation[:, :, 0], state.rotation[:, :, 1], state.rotation[:, :, 2]
    sensor_x = cos * hand_x + sin * hand_y
    sensor_z = side * (sin * hand_x - cos * hand_y)
    return np.stack([sensor_x, side * hand_z, sensor_z], axis=-1)


@dataclass(frozen=True)
class _PedalRest:
    """Per-pedal (n,) rest state: FSR preload resistance (ohm) and a lightly resting foot (N, Hz, rad)."""

    preload_ohm: np.ndarray
    foot_n: np.ndarray
    foot_hz: np.ndarray
    foot_phase_rad: np.ndarray


# ---------------------------------------------------------------------------------------------------
# the model


class SurgeonMotion:
    """Hands and feet of one simulated surgeon; every method takes t (N,) = seconds since device start."""

    def __init__(self, config: MotionConfig = MotionConfig()) -> None:
        self.config = config
        chunk_s = config.chunk_s
        self._focus_style = _ReachStyle(
            self._focus_targets, _focus_shift_duration, config.focus_hold_s, _FOCUS_SHIFT_BASE_S
        )
        self._reach_style = _ReachStyle(
            self._reach_targets, self._reach_duration, config.reach_hold_s, config.reach_base_s
        )
        self._focus = _KnotCurve(chunk_s, self._focus_chunk)
        self._reach = [_KnotCurve(chunk_s, lambda k, h=hand: self._reach_chunk(h, k)) for hand in range(2)]
        self._grasp = [_KnotCurve(chunk_s, lambda k, h=hand: self._grasp_chunk(h, k)) for hand in range(2)]
        self._presses = [
            _IntervalSchedule(chunk_s, lambda k, p=pedal: self._press_chunk(p, k))
            for pedal in range(len(config.pedal_profiles))
        ]
        self._occlusions = [
            _IntervalSchedule(chunk_s, lambda k, h=hand: self._occlusion_chunk(h, k)) for hand in range(2)
        ]
        self._fine = [_KnotCurve(chunk_s, lambda k, h=hand: self._fine_chunk(h, k)) for hand in range(2)]
        self._tremor = [self._draw_tremor(hand) for hand in range(2)]
        self._aperture_wobble = [self._draw_aperture_wobble(hand) for hand in range(2)]
        self._pedal_rest = self._draw_pedal_rest()

    # ---- public API ----------------------------------------------------------------------------

    def sensor_poses(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Poses of the 4 trakSTAR sensors (order ``SENSOR_NAMES``) in the transmitter frame.

        Returns positions (N, 4, 3) in mm and orientations (N, 4, 3) as azimuth, elevation, roll in
        degrees (azimuth and roll in [-180, 180), elevation in [-90, 90]). Noise-free apart from the
        physiological tremor: the device simulator adds measurement noise.
        """
        t = _as_times(t)
        positions, angles = np.empty((t.size, 4, 3)), np.empty((t.size, 4, 3))
        for sensor, state, side in self._grip_pads(t):
            positions[:, sensor] = self._pad_position(state, side)
            angles[:, sensor] = angles_from_matrices(_pad_rotation(state, side), wrap=True)
        return positions, angles

    def grasper_aperture(self, t: np.ndarray) -> np.ndarray:
        """Ground-truth thumb-middle sensor distance (N, 2) in mm for the (left, right) hand."""
        t = _as_times(t)
        return np.column_stack([self._aperture(t, hand) for hand in range(2)])

    def hand_keypoints(self, t: np.ndarray) -> np.ndarray:
        """Detected fingertips (N, 2, 2, 3): hand (``HAND_NAMES``) x keypoint (``KEYPOINT_NAMES``) x xyz, mm.

        In the camera frame (see ``camera_from_transmitter``), with ~3 mm detection noise; NaN for a
        whole hand where the detector misses it (isolated frames and occlusion runs).
        """
        t = _as_times(t)
        rotation, translation = self.camera_from_transmitter()
        sensors = self._sensor_positions(t)
        keypoints = apply_rigid(rotation, translation, sensors[:, np.array(_HAND_SENSORS)])
        keypoints += self._keypoint_noise(t)
        for hand in range(2):
            keypoints[self._keypoint_missed(t, hand), hand] = np.nan
        return keypoints

    def pedal_pressed(self, t: np.ndarray) -> np.ndarray:
        """Ground-truth press state (N, n_pedals) bool (True while the foot holds the pedal down)."""
        t = _as_times(t)
        return np.column_stack([self._presses[p].lookup(t)[1] for p in range(self.config.n_pedals)])

    def pedal_adc(self, t: np.ndarray) -> np.ndarray:
        """FSR divider readings (N, n_pedals) as 10-bit ADC counts 0..1023 (int32), Vcc = 5 V.

        Unpressed ~0-60 counts (mounting preload, resting foot, noise); pressed ~500-950 by force, with a
        few ms of contact bounce at press onset and release.
        """
        t = _as_times(t)
        t_us = _microseconds(t)
        counts = np.empty((t.size, self.config.n_pedals), dtype=np.int32)
        for pedal in range(self.config.n_pedals):
            force = self._press_force(t, pedal) + self._resting_foot_force(t, pedal)
            noise = _hash_normal(self.config.seed, _STREAM_ADC_NOISE + pedal, t_us) * self.config.adc_noise_counts
            counts[:, pedal] = self._fsr_counts(force, self._pedal_rest.preload_ohm[pedal], noise)
        return counts

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

    # ---- hands -------------------------------------------------------------------------------------

    def _hand_states(self, t: np.ndarray) -> list[_HandState]:
        """Grip point (mm, transmitter frame), rotation and grip half-opening of the (left, right) hand."""
        cfg = self.config
        focus = self._focus(t)
        states = []
        for hand in range(2):
            reach, fine = self._reach[hand](t), self._fine[hand](t)
            grip_point = self._neutral_grip_point(hand) + focus + reach[:, :3] + fine[:, :3]
            grip_point += self._tremor[hand](t)
            angles = self._wrist_base_deg(hand) + reach[:, 3:] + fine[:, 3:]
            half_angle = np.arcsin(self._aperture(t, hand) / (2.0 * cfg.grip_lever_mm))
            states.append(_HandState(grip_point, matrices_from_angles(angles), half_angle))
        return states

    def _neutral_grip_point(self, hand: int) -> np.ndarray:
        """Grip point (3,) mm that puts the hand's fingertips, half-open in the neutral wrist pose, at the
        workspace centre shifted laterally by half the hand separation."""
        cfg = self.config
        lateral = np.array([0.0, _HAND_LATERAL_SIGN[hand] * cfg.hand_separation_mm / 2, 0.0])
        typical_aperture = np.mean([cfg.aperture_open_mm, cfg.aperture_closed_mm])
        lever = cfg.grip_lever_mm * np.cos(np.arcsin(typical_aperture / (2.0 * cfg.grip_lever_mm)))
        hand_x = matrices_from_angles(self._wrist_base_deg(hand)[None])[0, :, 0]
        return np.asarray(cfg.workspace_centre_mm) + lateral - lever * hand_x

    def _wrist_base_deg(self, hand: int) -> np.ndarray:
        """Neutral (azimuth, elevation, roll) of a hand in degrees; the hands mirror each other."""
        azimuth, elevation, roll = self.config.wrist_base_deg
        mirror = -_HAND_LATERAL_SIGN[hand]
        return np.array([mirror * azimuth, elevation, mirror * roll])

    def _pad_position(self, state: _HandState, side: float) -> np.ndarray:
        """Position (N, 3) mm of the grip pad on hand-frame side ``side`` (+1 / -1 along y)."""
        lever = self.config.grip_lever_mm
        along = (lever * np.cos(state.half_angle))[:, None]
        across = (side * lever * np.sin(state.half_angle))[:, None]
        return state.grip_point + state.rotation[:, :, 0] * along + state.rotation[:, :, 1] * across

    def _grip_pads(self, t: np.ndarray) -> list[tuple[int, _HandState, float]]:
        """(sensor index, its hand's state, pad side +1/-1 along hand-frame y) for the 4 sensors."""
        pads = []
        for hand, state in enumerate(self._hand_states(t)):
            thumb, middle = _HAND_SENSORS[hand]
            pads += [(thumb, state, _THUMB_SIDE[hand]), (middle, state, -_THUMB_SIDE[hand])]
        return pads

    def _sensor_positions(self, t: np.ndarray) -> np.ndarray:
        """Sensor positions (N, 4, 3) mm, order ``SENSOR_NAMES``."""
        positions = np.empty((t.size, 4, 3))
        for sensor, state, side in self._grip_pads(t):
            positions[:, sensor] = self._pad_position(state, side)
        return positions

    def _aperture(self, t: np.ndarray, hand: int) -> np.ndarray:
        """Thumb-middle pad distance (N,) mm: grasp cycles plus a slow wobble."""
        return self._grasp[hand](t)[:, 0] + self._aperture_wobble[hand](t)[:, 0]

    def _knots_between_clutches(
        self, k: int, rng: np.random.Generator, style: _ReachStyle, boundary: Callable[[int], np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Knots in chunk k of a hold-and-reach process that moves back near zero during each clutch press.

        ``boundary(j)`` is the value at the start of chunk j. Between clutches the process reaches between
        random targets; a clutch press is one move from a random target to a near-neutral one.
        """
        clutch_starts, clutch_ends = self._clutch_intervals(k)
        span_starts = np.concatenate([[k * self.config.chunk_s], clutch_ends])
        span_ends = np.concatenate([clutch_starts, [(k + 1) * self.config.chunk_s]])
        recentred = _RECENTRED_FRACTION * style.draw_targets(rng, len(clutch_ends))
        start_values = np.vstack([boundary(k)[None], recentred])
        end_values = np.vstack([style.draw_targets(rng, len(clutch_starts)), boundary(k + 1)[None]])
        spans = zip(span_starts, span_ends, start_values, end_values)
        pieces = [style.knots(rng, (a, b), (va, vb)) for a, b, va, vb in spans]
        return np.concatenate([p[0] for p in pieces])[:-1], np.concatenate([p[1] for p in pieces])[:-1]

    def _clutch_intervals(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(starts, ends) s of the clutch presses in chunk k."""
        starts, ends, _ = self._press_chunk(CLUTCH_PEDAL, k)
        return starts, ends

    def _focus_chunk(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Knots (times, values (K, 3) mm) of the shared bimanual focus offset in chunk k."""
        rng = _rng(self.config.seed, _STREAM_FOCUS, k)
        return self._knots_between_clutches(k, rng, self._focus_style, self._focus_boundary)

    def _focus_targets(self, rng: np.random.Generator, count: int) -> np.ndarray:
        """Random focus offsets (count, 3) mm, uniform in ``focus_half_extent_mm``."""
        extent = np.asarray(self.config.focus_half_extent_mm)
        return rng.uniform(-extent, extent, (count, 3))

    def _focus_boundary(self, k: int) -> np.ndarray:
        """Focus offset (3,) mm at the start of chunk k."""
        return self._focus_targets(_rng(self.config.seed, _STREAM_FOCUS_BOUNDARY, k), 1)[0]

    def _reach_duration(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Duration (M,) s of reaches a -> b (M, 6: mm, deg), Fitts-like: base + distance / speed."""
        distance = np.linalg.norm(b[:, :3] - a[:, :3], axis=1)
        return self.config.reach_base_s + distance / self.config.reach_speed_mm_s

    def _reach_targets(self, rng: np.random.Generator, count: int) -> np.ndarray:
        """Random reach targets (count, 6): position offset mm, then wrist angle offsets deg.

        The wrist turns (azimuth) with the lateral offset and pitches (elevation) with the depth offset.
        """
        cfg = self.config
        extent, half_range = np.asarray(cfg.reach_half_extent_mm), np.asarray(cfg.wrist_half_range_deg)
        position = rng.uniform(-extent, extent, (count, 3))
        coupling = np.column_stack([-0.4 * position[:, 1], 0.3 * position[:, 0], np.zeros(count)])
        return np.hstack([position, coupling + rng.uniform(-half_range, half_range, (count, 3))])

    def _reach_boundary(self, hand: int, k: int) -> np.ndarray:
        """Reach offset (6,) of a hand at the start of chunk k."""
        return self._reach_targets(_rng(self.config.seed, _STREAM_REACH_BOUNDARY, hand, k), 1)[0]

    def _reach_chunk(self, hand: int, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Knots (times, values (K, 6): mm, deg) of a hand's reach/hold schedule in chunk k."""
        rng = _rng(self.config.seed, _STREAM_REACH, hand, k)
        return self._knots_between_clutches(k, rng, self._reach_style, lambda j: self._reach_boundary(hand, j))

    def _grasp_boundary(self, hand: int, k: int) -> float:
        """Open aperture (mm) of a hand at the start of chunk k."""
        rng = _rng(self.config.seed, _STREAM_GRASP_BOUNDARY, hand, k)
        return float(rng.uniform(*self.config.aperture_open_mm))

    def _grasp_chunk(self, hand: int, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Knots (times, apertures (K, 1) mm) of grasp cycles in chunk k: hold open, close, hold, open."""
        cfg = self.config
        t0, t1 = k * cfg.chunk_s, (k + 1) * cfg.chunk_s
        rng = _rng(cfg.seed, _STREAM_GRASP, hand, k)
        count = int(cfg.chunk_s / (cfg.grasp_open_hold_s[0] + cfg.grasp_closed_hold_s[0])) + 2
        opened, closed = rng.uniform(*cfg.aperture_open_mm, count), rng.uniform(*cfg.aperture_closed_mm, count)
        durations = np.column_stack([
            rng.uniform(*cfg.grasp_open_hold_s, count), rng.uniform(*cfg.grasp_transition_s, count),
            rng.uniform(*cfg.grasp_closed_hold_s, count), rng.uniform(*cfg.grasp_transition_s, count),
        ])
        start = self._grasp_boundary(hand, k)
        values = np.column_stack([np.concatenate([[start], opened[:-1]]), closed, closed, opened])
        cycle_ends = t0 + np.cumsum(durations.sum(axis=1))
        n = int(np.searchsorted(cycle_ends, t1 - _MIN_APERTURE_END_GAP_S, side="right"))
        times = t0 + np.cumsum(durations[:n].ravel())
        return np.concatenate([[t0], times]), np.concatenate([[start], values[:n].ravel()])[:, None]

    def _fine_targets(self, rng: np.random.Generator, count: int) -> np.ndarray:
        """Random fine-manipulation offsets (count, 6): position mm, then wrist angles deg."""
        cfg = self.config
        amplitude = np.array([cfg.fine_motion_mm] * 3 + [cfg.fine_rotation_deg] * 3)
        return rng.uniform(-amplitude, amplitude, (count, 6))

    def _fine_chunk(self, hand: int, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Knots (times, values (K, 6)) of small manipulation movements of a hand in chunk k."""
        cfg = self.config
        t0, t1 = k * cfg.chunk_s, (k + 1) * cfg.chunk_s
        rng = _rng(cfg.seed, _STREAM_FINE, hand, k)
        count = int(cfg.chunk_s / cfg.fine_interval_s[0]) + 2
        times = t0 + np.cumsum(rng.uniform(*cfg.fine_interval_s, count))
        keep = times < t1 - cfg.fine_interval_s[0]
        start = self._fine_targets(_rng(cfg.seed, _STREAM_FINE_BOUNDARY, hand, k), 1)
        return np.concatenate([[t0], times[keep]]), np.vstack([start, self._fine_targets(rng, count)[keep]])

    def _draw_tremor(self, hand: int) -> _SinusoidBank:
        """Physiological tremor (3 axes, mm): 2 components per axis in ``tremor_hz``."""
        cfg = self.config
        amplitudes = np.full((3, 2), cfg.tremor_mm)
        return _SinusoidBank.draw(_rng(cfg.seed, _STREAM_HAND_STATIC, hand, 1), cfg.tremor_hz, amplitudes)

    def _draw_aperture_wobble(self, hand: int) -> _SinusoidBank:
        """Slow variation of grip force on the pads (1 axis, mm), 0.2-0.6 Hz."""
        amplitudes = np.full((1, 2), self.config.aperture_wobble_mm)
        return _SinusoidBank.draw(_rng(self.config.seed, _STREAM_HAND_STATIC, hand, 2), (0.2, 0.6), amplitudes)

    # ---- keypoints ---------------------------------------------------------------------------------

    def _keypoint_noise(self, t: np.ndarray) -> np.ndarray:
        """Detection noise (N, 2, 2, 3) mm in the camera frame (per-axis sigma ``keypoint_noise_mm``)."""
        t_us = _microseconds(t)
        noise = np.empty((t.size, 2, 2, 3))
        for index in np.ndindex(2, 2, 3):
            stream = _STREAM_KEYPOINT_NOISE + int(np.ravel_multi_index(index, (2, 2, 3)))
            noise[:, index[0], index[1], index[2]] = _hash_normal(self.config.seed, stream, t_us)
        return noise * np.asarray(self.config.keypoint_noise_mm)

    def _keypoint_missed(self, t: np.ndarray, hand: int) -> np.ndarray:
        """(N,) bool: the detector misses this hand (isolated frame or occlusion run)."""
        isolated = _hash_uniform(self.config.seed, _STREAM_KEYPOINT_MISS + hand, _microseconds(t))
        return (isolated < self.config.keypoint_miss_probability) | self._occlusions[hand].lookup(t)[1]

    def _occlusion_chunk(self, hand: int, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(starts, ends) s of a hand's occlusion runs in chunk k."""
        cfg = self.config
        rng = _rng(cfg.seed, _STREAM_OCCLUSION, hand, k)
        return _renewal_events(rng, cfg.occlusion_profile, k * cfg.chunk_s, (k + 1) * cfg.chunk_s)

    # ---- pedals ------------------------------------------------------------------------------------

    def _press_chunk(self, pedal: int, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(starts, ends, params (M, 8)) of a pedal's presses in chunk k; params columns ``_PEAK_N`` ..."""
        cfg = self.config
        rng = _rng(cfg.seed, _STREAM_PEDAL, pedal, k)
        starts, ends = _renewal_events(rng, cfg.pedal_profiles[pedal], k * cfg.chunk_s, (k + 1) * cfg.chunk_s)
        count = len(starts)
        bounces = rng.choice(len(_BOUNCE_COUNT_PROBABILITIES), (count, 2), p=_BOUNCE_COUNT_PROBABILITIES)
        params = np.column_stack([
            np.exp(rng.uniform(*np.log(cfg.pedal_force_n), count)), bounces,
            rng.uniform(*cfg.bounce_window_s, (count, 2)), rng.uniform(*cfg.press_rise_s, (count, 2)),
            rng.uniform(0.0, 2.0 * np.pi, count),
        ])
        return starts, ends, params

    def _press_force(self, t: np.ndarray, pedal: int) -> np.ndarray:
        """Foot force (N,) in N on a pedal from its presses: ramp, hold with wobble, bounce at the edges."""
        index, inside = self._presses[pedal].lookup(t)
        force = np.zeros(t.size)
        if not inside.any():
            return force
        starts, ends, params = (field[index[inside]] for field in self._presses[pedal].fields_covering(t))
        since_on, until_off = t[inside] - starts, ends - t[inside]
        peak = params[:, _PEAK_N]
        ramp = np.minimum(since_on / params[:, _RISE_S], until_off / params[:, _FALL_S])
        amplitude, hz = _PRESS_WOBBLE
        wobble = 1.0 + amplitude * np.sin(2.0 * np.pi * hz * since_on + params[:, _WOBBLE_PHASE])
        held = np.maximum(peak * _minimum_jerk(np.clip(ramp, 0.0, 1.0)) * wobble, _CONTACT_FORCE_FRACTION * peak)
        onset_contact = _bounce_contact(since_on, params[:, _ON_BOUNCES], params[:, _ON_WINDOW_S])
        release_contact = _bounce_contact(until_off, params[:, _OFF_BOUNCES], params[:, _OFF_WINDOW_S])
        force[inside] = np.where(onset_contact & release_contact, held, 0.0)
        return force

    def _draw_pedal_rest(self) -> _PedalRest:
        """Per-pedal FSR preload and resting-foot parameters."""
        cfg = self.config
        rng = _rng(cfg.seed, _STREAM_PEDAL_STATIC)
        n = len(cfg.pedal_profiles)
        return _PedalRest(
            preload_ohm=np.exp(rng.uniform(*np.log(cfg.fsr_rest_ohm), n)),
            foot_n=rng.uniform(0.0, cfg.resting_foot_max_n, n),
            foot_hz=rng.uniform(0.02, 0.1, n),
            foot_phase_rad=rng.uniform(0.0, 2.0 * np.pi, n),
        )

    def _resting_foot_force(self, t: np.ndarray, pedal: int) -> np.ndarray:
        """Force (N,) in N of a foot resting lightly on a pedal between presses (slowly varying)."""
        rest = self._pedal_rest
        angle = 2.0 * np.pi * rest.foot_hz[pedal] * t + rest.foot_phase_rad[pedal]
        return rest.foot_n[pedal] * 0.5 * (1.0 - np.cos(angle))

    def _fsr_counts(self, force: np.ndarray, rest_ohm: float, noise: np.ndarray) -> np.ndarray:
        """ADC counts (N,) of the divider for force (N,) in N; R_fsr = R1 / F^n in parallel with the preload."""
        cfg = self.config
        conductance = 1.0 / rest_ohm + np.power(force, cfg.fsr_exponent) / cfg.fsr_ohm_at_1n  # siemens
        divider = cfg.fsr_series_ohm * conductance / (1.0 + cfg.fsr_series_ohm * conductance)  # Vout / Vcc
        return np.clip(np.floor(divider * 1024.0 + noise), 0, 1023).astype(np.int32)


def _bounce_contact(elapsed: np.ndarray, bounces: np.ndarray, window_s: np.ndarray) -> np.ndarray:
    """(N,) bool: foot in contact, ``elapsed`` s after onset (or before release).

    The first ``window_s`` s are split into 2 * bounces + 1 equal slots alternating contact / gap.
    """
    slot = np.floor(elapsed / window_s * (2.0 * bounces + 1.0))
    return (slot % 2.0 == 0.0) | (slot > 2.0 * bounces)


def _as_times(t: np.ndarray) -> np.ndarray:
    """Validated sample times: 1-D float64 array of finite values >= 0 (s since device start)."""
    times = np.atleast_1d(np.asarray(t, dtype=np.float64))
    if times.ndim != 1:
        raise ValueError(f"t must be 1-D, got shape {times.shape}")
    if times.size and not (np.isfinite(times).all() and times.min() >= 0.0):
        raise ValueError("t must be finite and >= 0 (seconds since the simulated device started)")
    return times
