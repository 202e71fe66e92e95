"""The simulated surgeon's hands on the master-controller grips.

Each hand holds a grip, a hinge ("grip point") with two levers of ``grip_lever_mm``; the thumb and
middle-finger trakSTAR sensors sit on the lever pads. The grip point is the sum of a shared, slowly
shifting bimanual focus, per-hand minimum-jerk reaches between random targets with holds (position and
wrist angles together), small fine-manipulation movements and 8-12 Hz tremor. During each clutch press
the focus and both hands move back near the workspace middle. The grip opens and closes in grasp cycles.

Frame: trakSTAR transmitter frame, mm (x = depth, y = lateral, surgeon's right positive, z = down).
Clock: ``t`` is seconds since the simulated device started.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

from midas_cli.geometry import matrices_from_angles
from midas_cli.synthetic.noise import SinusoidBank, seeded_rng
from midas_cli.synthetic.schedule import KnotCurve, ReachStyle

if TYPE_CHECKING:
    from midas_cli.synthetic.surgeon import MotionConfig

SENSOR_NAMES = ("left_middle", "left_thumb", "right_thumb", "right_middle")  # trakSTAR sensors 1..4
HAND_NAMES = ("left", "right")
HAND_SENSORS = ((1, 0), (2, 3))  # per hand: (thumb, middle) indices into SENSOR_NAMES
THUMB_SIDE = (1.0, -1.0)  # per hand: hand-frame y side of the thumb pad (medial, towards the midline)
_HAND_LATERAL_SIGN = (-1.0, 1.0)
_MIN_APERTURE_END_GAP_S = 0.5
_FOCUS_SHIFT_BASE_S = 0.8  # duration of a focus shift: base + distance / speed
_FOCUS_SHIFT_SPEED_MM_S = 40.0
_RECENTRED_FRACTION = 0.15  # after a clutch press, offsets are this fraction of a random target

# stream ids: each random schedule draws from its own (seed, stream, ...) key
_STREAM_FOCUS = 1
_STREAM_FOCUS_BOUNDARY = 2
_STREAM_REACH = 10
_STREAM_REACH_BOUNDARY = 12
_STREAM_GRASP = 20
_STREAM_GRASP_BOUNDARY = 22
_STREAM_HAND_STATIC = 60
_STREAM_FINE = 62
_STREAM_FINE_BOUNDARY = 64


@dataclass(frozen=True)
class HandState:
    """One hand at N times: grip point (N, 3) mm, hand rotation (N, 3, 3), grip half-opening (N,) rad."""

    grip_point: np.ndarray
    rotation: np.ndarray
    half_angle: np.ndarray


def pad_rotation(state: HandState, side: float) -> np.ndarray:
    """Sensor rotations (N, 3, 3) on the pad at ``side`` (+1 / -1 along hand-frame y).

    hand rotation @ Rz(side * half_angle) @ Rx(side * 90 deg): sensor x runs along the lever, sensor z is
    the pad normal pointing at the other pad.
    """
    cos, sin = np.cos(state.half_angle)[:, None], side * np.sin(state.half_angle)[:, None]
    hand_x, hand_y, hand_z = state.rotation[:, :, 0], state.rotation[:, :, 1], state.rotation[:, :, 2]
    sensor_x = cos * hand_x + sin * hand_y
    sensor_z = side * (sin * hand_x - cos * hand_y)
    return np.stack([sensor_x, side * hand_z, sensor_z], axis=-1)


def focus_shift_duration(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Duration (M,) s of slow shifts of the bimanual focus a -> b (M, 3) mm."""
    return _FOCUS_SHIFT_BASE_S + np.linalg.norm(b - a, axis=1) / _FOCUS_SHIFT_SPEED_MM_S


class HandModel:
    """Both hands of one simulated surgeon; every method takes t (N,) = seconds since device start.

    ``clutch_intervals(k)`` gives the (starts, ends) s of the clutch presses in chunk k (the feet's).
    """

    def __init__(self, config: MotionConfig, clutch_intervals: Callable[[int], tuple[np.ndarray, np.ndarray]]
                 ) -> None:
        self.config = config
        chunk_s = config.chunk_s
        self._clutch_intervals = clutch_intervals
        self._focus_style = ReachStyle(
            self._focus_targets, focus_shift_duration, config.focus_hold_s, _FOCUS_SHIFT_BASE_S
        )
        self._reach_style = ReachStyle(
            self._reach_targets, self._reach_duration, config.reach_hold_s, config.reach_base_s
        )
        self._focus = KnotCurve(chunk_s, self._focus_chunk)
        self._reach = [KnotCurve(chunk_s, lambda k, h=hand: self._reach_chunk(h, k)) for hand in range(2)]
        self._grasp = [KnotCurve(chunk_s, lambda k, h=hand: self._grasp_chunk(h, k)) for hand in range(2)]
        self._fine = [KnotCurve(chunk_s, lambda k, h=hand: self._fine_chunk(h, k)) for hand in range(2)]
        self._tremor = [self._draw_tremor(hand) for hand in range(2)]
        self._aperture_wobble = [self._draw_aperture_wobble(hand) for hand in range(2)]

    def states(self, t: np.ndarray) -> list[HandState]:
        """Grip point (mm, transmitter frame), rotation and grip half-opening of the (left, right) hand."""
        cfg = self.config
        focus = self._focus(t)
        states = []
        for hand in range(2):
            reach, fine = self._reach[hand](t), self._fine[hand](t)
            grip_point = self.neutral_grip_point(hand) + focus + reach[:, :3] + fine[:, :3]
            grip_point += self._tremor[hand](t)
            angles = self.wrist_base_deg(hand) + reach[:, 3:] + fine[:, 3:]
            half_angle = np.arcsin(self.aperture(t, hand) / (2.0 * cfg.grip_lever_mm))
            states.append(HandState(grip_point, matrices_from_angles(angles), half_angle))
        return states

    def neutral_grip_point(self, hand: int) -> np.ndarray:
        """Grip point (3,) mm that puts the hand's fingertips, half-open in the neutral wrist pose, at the
        workspace centre shifted laterally by half the hand separation."""
        cfg = self.config
        lateral = np.array([0.0, _HAND_LATERAL_SIGN[hand] * cfg.hand_separation_mm / 2, 0.0])
        typical_aperture = np.mean([cfg.aperture_open_mm, cfg.aperture_closed_mm])
        lever = cfg.grip_lever_mm * np.cos(np.arcsin(typical_aperture / (2.0 * cfg.grip_lever_mm)))
        hand_x = matrices_from_angles(self.wrist_base_deg(hand)[None])[0, :, 0]
        return np.asarray(cfg.workspace_centre_mm) + lateral - lever * hand_x

    def wrist_base_deg(self, hand: int) -> np.ndarray:
        """Neutral (azimuth, elevation, roll) of a hand in degrees; the hands mirror each other."""
        azimuth, elevation, roll = self.config.wrist_base_deg
        mirror = -_HAND_LATERAL_SIGN[hand]
        return np.array([mirror * azimuth, elevation, mirror * roll])

    def pad_position(self, state: HandState, side: float) -> np.ndarray:
        """Position (N, 3) mm of the grip pad on hand-frame side ``side`` (+1 / -1 along y)."""
        lever = self.config.grip_lever_mm
        along = (lever * np.cos(state.half_angle))[:, None]
        across = (side * lever * np.sin(state.half_angle))[:, None]
        return state.grip_point + state.rotation[:, :, 0] * along + state.rotation[:, :, 1] * across

    def grip_pads(self, t: np.ndarray) -> list[tuple[int, HandState, float]]:
        """(sensor index, its hand's state, pad side +1/-1 along hand-frame y) for the 4 sensors."""
        pads = []
        for hand, state in enumerate(self.states(t)):
            thumb, middle = HAND_SENSORS[hand]
            pads += [(thumb, state, THUMB_SIDE[hand]), (middle, state, -THUMB_SIDE[hand])]
        return pads

    def sensor_positions(self, t: np.ndarray) -> np.ndarray:
        """Sensor positions (N, 4, 3) mm, order ``SENSOR_NAMES``."""
        positions = np.empty((t.size, 4, 3))
        for sensor, state, side in self.grip_pads(t):
            positions[:, sensor] = self.pad_position(state, side)
        return positions

    def aperture(self, t: np.ndarray, hand: int) -> np.ndarray:
        """Thumb-middle pad distance (N,) mm: grasp cycles plus a slow wobble."""
        return self._grasp[hand](t)[:, 0] + self._aperture_wobble[hand](t)[:, 0]

    def _knots_between_clutches(
        self, k: int, rng: np.random.Generator, style: ReachStyle, boundary: Callable[[int], np.ndarray]
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

    def _focus_chunk(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Knots (times, values (K, 3) mm) of the shared bimanual focus offset in chunk k."""
        rng = seeded_rng(self.config.seed, _STREAM_FOCUS, k)
        return self._knots_between_clutches(k, rng, self._focus_style, self._focus_boundary)

    def _focus_targets(self, rng: np.random.Generator, count: int) -> np.ndarray:
        """Random focus offsets (count, 3) mm, uniform in ``focus_half_extent_mm``."""
        extent = np.asarray(self.config.focus_half_extent_mm)
        return rng.uniform(-extent, extent, (count, 3))

    def _focus_boundary(self, k: int) -> np.ndarray:
        """Focus offset (3,) mm at the start of chunk k."""
        return self._focus_targets(seeded_rng(self.config.seed, _STREAM_FOCUS_BOUNDARY, k), 1)[0]

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
        return self._reach_targets(seeded_rng(self.config.seed, _STREAM_REACH_BOUNDARY, hand, k), 1)[0]

    def _reach_chunk(self, hand: int, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Knots (times, values (K, 6): mm, deg) of a hand's reach/hold schedule in chunk k."""
        rng = seeded_rng(self.config.seed, _STREAM_REACH, hand, k)
        return self._knots_between_clutches(k, rng, self._reach_style, lambda j: self._reach_boundary(hand, j))

    def _grasp_boundary(self, hand: int, k: int) -> float:
        """Open aperture (mm) of a hand at the start of chunk k."""
        rng = seeded_rng(self.config.seed, _STREAM_GRASP_BOUNDARY, hand, k)
        return float(rng.uniform(*self.config.aperture_open_mm))

    def _grasp_chunk(self, hand: int, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Knots (times, apertures (K, 1) mm) of grasp cycles in chunk k: hold open, close, hold, open."""
        cfg = self.config
        t0, t1 = k * cfg.chunk_s, (k + 1) * cfg.chunk_s
        rng = seeded_rng(cfg.seed, _STREAM_GRASP, hand, k)
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
        rng = seeded_rng(cfg.seed, _STREAM_FINE, hand, k)
        count = int(cfg.chunk_s / cfg.fine_interval_s[0]) + 2
        times = t0 + np.cumsum(rng.uniform(*cfg.fine_interval_s, count))
        keep = times < t1 - cfg.fine_interval_s[0]
        start = self._fine_targets(seeded_rng(cfg.seed, _STREAM_FINE_BOUNDARY, hand, k), 1)
        return np.concatenate([[t0], times[keep]]), np.vstack([start, self._fine_targets(rng, count)[keep]])

    def _draw_tremor(self, hand: int) -> SinusoidBank:
        """Physiological tremor (3 axes, mm): 2 components per axis in ``tremor_hz``."""
        cfg = self.config
        amplitudes = np.full((3, 2), cfg.tremor_mm)
        return SinusoidBank.draw(seeded_rng(cfg.seed, _STREAM_HAND_STATIC, hand, 1), cfg.tremor_hz, amplitudes)

    def _draw_aperture_wobble(self, hand: int) -> SinusoidBank:
        """Slow variation of grip force on the pads (1 axis, mm), 0.2-0.6 Hz."""
        amplitudes = np.full((1, 2), self.config.aperture_wobble_mm)
        return SinusoidBank.draw(seeded_rng(self.config.seed, _STREAM_HAND_STATIC, hand, 2), (0.2, 0.6), amplitudes)
