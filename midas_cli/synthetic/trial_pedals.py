"""Foot pedal presses of simulated trials and the FSR board's readings of them.

FPS channel k = the paper's "Pedal k" (1 secondary energy L, 2 secondary energy R, 3 primary energy L,
4 primary energy R, 5 clutch, 6 camera, 7 arm swap; 8, 9 unmapped). Raven-II: only the clutch.
da Vinci Xi suturing, after the paper's pedal usage table: the camera pedal dominates, primary energy
right is the most used energy pedal, secondary energy right is rare, the foot clutch is rare (the
surgeons used the finger clutch), channels 1, 3 and 7 are never pressed.
"""

from __future__ import annotations

import numpy as np

from midas_cli.devices.pedals import adc_to_volts
from midas_cli.synthetic.feet import bounce_contact
from midas_cli.synthetic.schedule import minimum_jerk
from midas_cli.synthetic.surgeon import MotionConfig, SurgeonMotion

N_CHANNELS = 9
CLUTCH = 5
CAMERA = 6
# channel: (presses per minute, min s, max s) for the random (Poisson) pedals on the da Vinci
DAVINCI_RANDOM = {CAMERA: (3.2, 1.0, 4.0), 4: (0.55, 0.3, 1.5), 2: (0.05, 0.3, 1.2)}
CLUTCH_PROBABILITY = {"raven-ii": 0.4, "davinci-xi": 0.01}  # per gesture segment start
CLUTCH_LABELS = {"raven-ii": ("Idle", "S1", "S4", "S6"), "davinci-xi": ("G1", "G2", "G5")}
PRESS_V, RELEASE_V = 1.5, 1.0  # thresholds of the pressed columns (the simulated rig's defaults)


def clutch_intervals(rng: np.random.Generator, platform: str, segments: list[tuple[str, float, float]]
                     ) -> np.ndarray:
    """(M, 2) s: clutch presses starting 0.1-0.4 s into some gesture segments, released inside them."""
    rows = []
    for label, t0, t1 in segments:
        duration = rng.uniform(0.5, 1.5)
        if label in CLUTCH_LABELS[platform] and rng.random() < CLUTCH_PROBABILITY[platform] and t1 - t0 > duration + 1.5:
            start = t0 + rng.uniform(0.1, 0.4)
            rows.append((start, start + duration))
    return np.array(rows).reshape(-1, 2)


def random_presses(rng: np.random.Generator, rate_per_min: float, span: tuple[float, float],
                   total_s: float) -> np.ndarray:
    """(M, 2) s of non-overlapping presses: Poisson count, uniform starts, uniform durations."""
    count = rng.poisson(rate_per_min * total_s / 60.0)
    starts = np.sort(rng.uniform(0.5, max(total_s - span[1] - 0.5, 0.6), count))
    ends = starts + rng.uniform(*span, count)
    keep = np.concatenate([[True], starts[1:] > ends[:-1] + 0.3]) if count else np.zeros(0, bool)
    return np.column_stack([starts[keep], ends[keep]])


def pedal_schedule(rng: np.random.Generator, platform: str, clutches: np.ndarray, total_s: float
                   ) -> dict[int, np.ndarray]:
    """Pressed intervals (M, 2) s per FPS channel 1..9."""
    schedule = {k: np.zeros((0, 2)) for k in range(1, N_CHANNELS + 1)}
    schedule[CLUTCH] = clutches
    if platform == "davinci-xi":
        for channel, (rate, low, high) in DAVINCI_RANDOM.items():
            schedule[channel] = random_presses(rng, rate, (low, high), total_s)
    return schedule


def pressed_at(intervals: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N,) bool: t inside one of the (M, 2) intervals (sorted, non-overlapping)."""
    if not len(intervals):
        return np.zeros(len(t), dtype=bool)
    index = np.searchsorted(intervals[:, 0], t, side="right") - 1
    return (index >= 0) & (t < intervals[np.maximum(index, 0), 1])


def fsr_adc(intervals: np.ndarray, t: np.ndarray, rng: np.random.Generator, rig: SurgeonMotion) -> np.ndarray:
    """10-bit ADC counts (N,) of one pedal's FSR divider: force ramps up in 20-60 ms, wobbles while held,
    bounces at the edges; the simulated rig's FSR and divider model."""
    force = rng.uniform(0.0, 0.02) * np.ones(len(t))
    if len(intervals):
        index = np.clip(np.searchsorted(intervals[:, 0], t, side="right") - 1, 0, len(intervals) - 1)
        start, end = intervals[index, 0], intervals[index, 1]
        inside = (t >= start) & (t < end)
        peak = np.exp(rng.uniform(np.log(4.0), np.log(40.0), len(intervals)))[index]
        rise = rng.uniform(0.02, 0.06, len(intervals))[index]
        ramp = minimum_jerk(np.clip(np.minimum(t - start, end - t) / rise, 0.0, 1.0))
        bounces = rng.integers(0, 3, len(intervals))[index]
        contact = bounce_contact(t - start, bounces, 0.006) & bounce_contact(end - t, bounces, 0.006)
        held = peak * np.maximum(ramp, 0.3) * (1.0 + 0.06 * np.sin(2 * np.pi * 1.3 * (t - start)))
        force = np.where(inside & contact, held, force)
    noise = rng.normal(0.0, rig.config.adc_noise_counts, len(t))
    return rig.feet.fsr_counts(force, float(np.exp(rng.uniform(np.log(2e5), np.log(2e6)))), noise)


def hysteresis(volts: np.ndarray, press_v: float = PRESS_V, release_v: float = RELEASE_V) -> np.ndarray:
    """Pressed state (N, C) int from voltages (N, C): set at >= press_v, cleared at <= release_v, else held
    (vectorised equivalent of midas_cli.devices.pedals.PedalStateTracker, starting released)."""
    event = np.where(volts >= press_v, 1, np.where(volts <= release_v, 0, -1))
    index = np.where(event >= 0, np.arange(len(volts))[:, None], -1)
    last = np.maximum.accumulate(index, axis=0)
    state = np.take_along_axis(event, np.maximum(last, 0), axis=0)
    return np.where(last >= 0, state, 0)


def fps_block(schedule: dict[int, np.ndarray], t: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(adc (N, 9) int, pressed (N, 9) int) at true times t (N,) s."""
    rig = SurgeonMotion(MotionConfig(seed=seed))
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7003]))
    adc = np.column_stack([fsr_adc(schedule[k], t, rng, rig) for k in range(1, N_CHANNELS + 1)])
    return adc, hysteresis(adc_to_volts(adc))
