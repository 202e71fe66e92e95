"""Hand motion driven by a gesture sequence: each gesture has its own kinematic signature.

Every gesture prescribes, per hand, where the grip point goes (offset from the hand's home position in
the EmHT transmitter frame, mm), the wrist angles (azimuth, elevation, roll offsets, deg), a wrist roll
sweep during the gesture (needle driving), a circular motion (loops, cinching), the amplitude of small
manipulation movements, and grasp events (fraction of the gesture, open/closed). Moves are
minimum-jerk; on top come slow manipulation movements and 8-12 Hz tremor. During a clutch press the
hands move back towards home. Hand geometry (grip levers, sensor pads, wrist neutral pose, home
position) is the simulated rig's (midas_cli.synthetic.hands), so sensors sit where the live
simulator puts them.

A subject style (optional, from simulate/style.py, duck-typed: this package never imports simulate/)
scales and biases each plan, may swap the hands' roles (left-handed, mirrored), sets move speed, tremor
and fine-motion scale, and starts each move towards the next gesture before the segment ends
(blending); a sensor placement (optional) offsets each sensor on its pad.

Clock: ``t`` is seconds since the trial started (true time, before any sensor latency).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from midas_cli.geometry import matrices_from_angles
from midas_cli.synthetic.hands import HAND_SENSORS, THUMB_SIDE, HandState, pad_rotation
from midas_cli.synthetic.noise import SinusoidBank
from midas_cli.synthetic.schedule import minimum_jerk
from midas_cli.synthetic.surgeon import MotionConfig, SurgeonMotion

MOVE_BASE_S = 0.35
MOVE_SPEED_MM_S = 140.0
GRASP_TRANSITION_S = 0.25
APERTURE_OPEN_MM = (60.0, 80.0)
APERTURE_CLOSED_MM = (17.0, 25.0)
TREMOR_MM = 0.12
OSCILLATION_HZ = 0.6


@dataclass(frozen=True)
class HandPlan:
    """What one hand does during one gesture (None offset = stay where it is)."""

    offset_mm: tuple[float, float, float] | None = None
    spread_mm: float = 4.0
    wrist_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    roll_sweep_deg: float = 0.0
    circle_mm: float = 0.0
    fine_mm: float = 0.6
    grasp: tuple[tuple[float, str], ...] = field(default=())


H = HandPlan
# (left, right) per gesture. Offsets: x depth (away from the transmitter), y lateral (right +), z down +.
GESTURE_PLANS: dict[str, tuple[HandPlan, HandPlan]] = {
    "Idle": (H((0, 0, 0), 2, fine_mm=0.3, grasp=((0.3, "open"),)), H((0, 0, 0), 2, fine_mm=0.3, grasp=((0.3, "open"),))),
    "S1": (H((35, -25, -10), 8, (-10, 5, 0), grasp=((0.1, "open"),)), H()),
    "S2": (H((42, -25, 5), 4, (-10, 10, 15), fine_mm=2.0, grasp=((0.75, "closed"),)), H()),
    "S3": (H((40, -20, -35), 5, (0, -10, 10)), H()),
    "S4": (H((15, 30, -20), 6, (15, 0, 0)), H((15, -30, -20), 6, (-15, 0, 0), grasp=((0.2, "open"),))),
    "S5": (H((15, 35, -20), 3, (15, 0, -20), fine_mm=2.0, grasp=((0.7, "open"),)),
           H((15, -35, -20), 3, (-15, 0, 25), fine_mm=2.0, grasp=((0.35, "closed"),))),
    "S6": (H((0, 0, 0), 6, grasp=((0.2, "open"),)), H((35, 30, -15), 8, (5, 5, 0))),
    "S7": (H(), H((40, 32, 10), 4, (5, 10, 0), fine_mm=2.0, grasp=((0.8, "open"),))),
    "G1": (H((10, 20, -5), 5, (10, 0, 0), grasp=((0.1, "closed"),)),
           H((10, -20, -5), 5, (-10, 0, 0), 40.0, fine_mm=1.5, grasp=((0.2, "open"), (0.7, "closed")))),
    "G2": (H((15, 0, 0), 6), H((30, 10, 10), 12, (0, 10, -20), fine_mm=1.0, grasp=((0.1, "closed"),))),
    "G3": (H((15, 5, 0), 4), H((35, 5, 15), 5, (0, 15, -30), 80.0, grasp=((0.05, "closed"),))),
    "G4": (H((25, 30, -20), 6, (15, 0, 0), grasp=((0.4, "closed"),)), H((20, 0, 0), 4, grasp=((0.5, "open"),))),
    "G5": (H((45, -25, 10), 10, (-10, 10, 0), grasp=((0.1, "open"), (0.85, "closed"))), H((10, 0, 0), 4)),
    "G6": (H((-10, -50, -35), 15, (-20, -10, 0), fine_mm=1.5, grasp=((0.05, "closed"),)), H((0, 10, -10), 6)),
    "G7": (H((20, 20, 0), 4, grasp=((0.05, "closed"),)),
           H((15, -10, -5), 4, (0, 0, 0), -60.0, 15.0, grasp=((0.1, "closed"),))),
    "G8": (H((10, -45, -10), 8, circle_mm=5.0, grasp=((0.1, "closed"),)),
           H((10, 45, -10), 8, circle_mm=5.0, grasp=((0.1, "closed"),))),
}


PAUSE = "__pause__"  # motion key of a mid-trial pause: the hands stay where they are, almost still
PAUSE_PLAN = (HandPlan(spread_mm=0.0, fine_mm=0.3), HandPlan(spread_mm=0.0, fine_mm=0.3))


def knot_curve(times: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Minimum-jerk interpolation through knots (times (K,) increasing, values (K, D)) at t (N,) -> (N, D);
    constant before the first and after the last knot."""
    if len(times) == 1:
        return np.repeat(values[:1], len(t), axis=0)
    start = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    span = times[start + 1] - times[start]
    progress = minimum_jerk(np.clip((t - times[start]) / span, 0.0, 1.0))
    return values[start] + (values[start + 1] - values[start]) * progress[:, None]


@dataclass
class _HandKnots:
    """Knot lists of one hand: pose (x, y, z mm, azimuth, elevation, roll deg) and aperture (mm)."""

    pose_t: list[float]
    pose_v: list[np.ndarray]
    grip_t: list[float]
    grip_v: list[float]

    def add_pose(self, time: float, value: np.ndarray) -> None:
        if time > self.pose_t[-1] + 1e-6:
            self.pose_t.append(time)
            self.pose_v.append(value)

    def add_grip(self, time: float, value: float) -> None:
        if time > self.grip_t[-1] + 1e-6:
            self.grip_t.append(time)
            self.grip_v.append(value)


class GestureHands:
    """Both hands of one simulated trial, built from (label, start s, end s) segments and clutch intervals."""

    def __init__(self, segments: list[tuple[str, float, float]], clutches: np.ndarray, seed: int,
                 style: Any = None, placement: Any = None, gesture_index: dict[str, int] | None = None) -> None:
        """``style`` (a subject style, simulate/style.py) and ``placement`` (sensor placement) are None
        for the easy simulator; ``gesture_index`` maps a gesture label to its row in the style's biases."""
        self.rig = SurgeonMotion(MotionConfig(seed=seed))
        self.lever_mm = self.rig.config.grip_lever_mm
        rng = np.random.default_rng(np.random.SeedSequence([seed, 7001]))
        self.style, self.placement, self._gesture_index = style, placement, gesture_index or {}
        self.home = [self.rig.hands.neutral_grip_point(h) for h in range(2)]
        self.wrist_base = [self.rig.hands.wrist_base_deg(h) for h in range(2)]
        self.segments = segments
        self._bounds = np.array([s[1] for s in segments] + [segments[-1][2]])
        self._knots = [self._plan_hand(h, rng, clutches) for h in range(2)]
        self._circle = np.array([[self.plan(s[0], h).circle_mm for h in range(2)] for s in segments])
        self._fine = np.array([[self.plan(s[0], h).fine_mm for h in range(2)] for s in segments])
        tremor, fine = (1.0, 1.0) if style is None else (style.tremor, style.fine)
        self._slow = [SinusoidBank.draw(rng, (0.2, 1.2), np.full((3, 3), fine)) for _ in range(2)]
        self._tremor = [SinusoidBank.draw(rng, (8.0, 12.0), np.full((3, 2), TREMOR_MM * tremor)) for _ in range(2)]

    def plan(self, label: str, hand: int) -> HandPlan:
        """The plan of ``hand`` in gesture ``label``: a left-handed subject does the other hand's part,
        mirrored (lateral offset, azimuth and roll negated); the subject's amplitude and bias applied."""
        if label == PAUSE:
            return PAUSE_PLAN[hand]
        style = self.style
        if style is None:
            return GESTURE_PLANS[label][hand]
        plan = GESTURE_PLANS[label][1 - hand if style.left_handed else hand]
        mirror = np.array([1.0, -1.0, 1.0]) if style.left_handed else np.ones(3)
        bias = self._gesture_index.get(label)
        wrist = np.asarray(plan.wrist_deg) * np.array([mirror[1], 1.0, mirror[1]])
        offset = plan.offset_mm
        if offset is not None:
            offset = tuple(np.asarray(offset) * mirror * style.amplitude
                           + (style.bias_mm[bias, hand] if bias is not None else 0.0))
            wrist = wrist + (style.bias_deg[bias, hand] if bias is not None else 0.0)
        return replace(plan, offset_mm=offset, wrist_deg=tuple(wrist), spread_mm=plan.spread_mm * style.consistency,
                       roll_sweep_deg=plan.roll_sweep_deg * mirror[1] * style.amplitude,
                       circle_mm=plan.circle_mm * style.amplitude)

    def _plan_hand(self, hand: int, rng: np.random.Generator, clutches: np.ndarray) -> _HandKnots:
        t_start = self.segments[0][1]
        aperture = float(rng.uniform(*APERTURE_OPEN_MM))
        knots = _HandKnots([t_start], [np.zeros(6)], [t_start], [aperture])
        speed = MOVE_SPEED_MM_S * (1.0 if self.style is None else self.style.speed)
        for i, (label, t0, t1) in enumerate(self.segments):
            plan = self.plan(label, hand)
            begin = self._clutch_recentre(knots, clutches, t0, t1)
            current = knots.pose_v[-1]
            target = current.copy()
            if plan.offset_mm is not None:
                target[:3] = np.asarray(plan.offset_mm) + rng.normal(0.0, plan.spread_mm, 3)
                target[3:] = np.asarray(plan.wrist_deg) + rng.normal(0.0, 3.0, 3)
            move = min(0.5 * (t1 - begin), MOVE_BASE_S + np.linalg.norm(target[:3] - current[:3]) / speed)
            knots.add_pose(begin + move, target)
            swept = target + np.array([0, 0, 0, 0, 0, plan.roll_sweep_deg])
            knots.add_pose(t1 - self._blend(i, t0, t1), swept)
            for fraction, state in plan.grasp:
                self._grasp(knots, rng, t0 + fraction * (t1 - t0), state, t1)
        return knots

    def _blend(self, index: int, t0: float, t1: float) -> float:
        """How long before the segment's end the move towards the next gesture starts (0: at the end)."""
        if self.style is None or index == len(self.segments) - 1:
            return 0.0
        return min(self.style.blend_s, 0.3 * (t1 - t0))

    def _clutch_recentre(self, knots: _HandKnots, clutches: np.ndarray, t0: float, t1: float) -> float:
        """If a clutch press starts in this segment, move towards home while it is held; returns the
        time from which the gesture's own move starts."""
        inside = clutches[(clutches[:, 0] >= t0) & (clutches[:, 1] < t1)] if len(clutches) else clutches
        if not len(inside):
            return t0
        start, end = inside[0]
        knots.add_pose(start, knots.pose_v[-1])
        recentred = knots.pose_v[-1] * 0.15
        knots.add_pose(end, recentred)
        return end

    def _grasp(self, knots: _HandKnots, rng: np.random.Generator, when: float, state: str, t1: float) -> None:
        value = rng.uniform(*(APERTURE_OPEN_MM if state == "open" else APERTURE_CLOSED_MM))
        duration = min(GRASP_TRANSITION_S, 0.5 * (t1 - when))
        knots.add_grip(when, knots.grip_v[-1])
        knots.add_grip(when + duration, float(value))

    # ---- evaluation --------------------------------------------------------------------------------

    def states(self, t: np.ndarray) -> list[HandState]:
        """Grip point (N, 3) mm, rotation (N, 3, 3) and grip half-angle (N,) rad of (left, right)."""
        segment = np.clip(np.searchsorted(self._bounds, t, side="right") - 1, 0, len(self.segments) - 1)
        t0, t1 = self._bounds[segment], self._bounds[segment + 1]
        taper = np.sin(np.pi * np.clip((t - t0) / (t1 - t0), 0.0, 1.0)) ** 2
        mid = 0.5 * (self._bounds[:-1] + self._bounds[1:])
        states = []
        for hand in range(2):
            knots = self._knots[hand]
            pose = knot_curve(np.array(knots.pose_t), np.array(knots.pose_v), t)
            phase = 2.0 * np.pi * OSCILLATION_HZ * (t - t0)
            circle = (self._circle[segment, hand] * taper)[:, None] * np.column_stack(
                [np.sin(phase), np.cos(phase) - 1.0, 0.3 * np.sin(2 * phase)])
            fine = np.interp(t, mid, self._fine[:, hand])[:, None] * self._slow[hand](t)
            grip = self.home[hand] + pose[:, :3] + circle + fine + self._tremor[hand](t)
            rotation = matrices_from_angles(self.wrist_base[hand] + pose[:, 3:])
            aperture = knot_curve(np.array(knots.grip_t), np.array(knots.grip_v)[:, None], t)[:, 0]
            states.append(HandState(grip, rotation, np.arcsin(aperture / (2.0 * self.lever_mm))))
        return states

    def sensors(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[HandState]]:
        """Sensor positions (N, 4, 3) mm and rotations (N, 4, 3, 3), order 1 left middle, 2 left thumb,
        3 right thumb, 4 right middle (transmitter frame; as placed on the fingers in this session), and the
        hand states they came from."""
        states = self.states(t)
        positions, rotations = np.empty((len(t), 4, 3)), np.empty((len(t), 4, 3, 3))
        for hand, state in enumerate(states):
            thumb, middle = HAND_SENSORS[hand]
            for sensor, side in ((thumb, THUMB_SIDE[hand]), (middle, -THUMB_SIDE[hand])):
                positions[:, sensor] = self.rig.hands.pad_position(state, side)
                rotations[:, sensor] = pad_rotation(state, side)
        if self.placement is not None:
            positions, rotations = self.placement.apply(positions, rotations)
        return positions, rotations, states
