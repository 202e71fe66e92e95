"""The simulated surgeon's feet on a 9-channel FSR pedal board.

Per pedal, a renewal process of presses; force -> FSR resistance (power law) -> voltage divider
``Vout = R / (R + R_fsr) * Vcc`` (Vcc = 5 V) -> 10-bit ADC counts, with contact bounce at the edges of
each press and a lightly resting foot between presses. Clock: ``t`` is seconds since the simulated
device started.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from midas_cli.synthetic.noise import hash_normal, microseconds, seeded_rng
from midas_cli.synthetic.schedule import EventProfile, IntervalSchedule, minimum_jerk, renewal_events

if TYPE_CHECKING:
    from midas_cli.synthetic.surgeon import MotionConfig

N_PEDALS = 9
CLUTCH_PEDAL = 4  # 0-based FPS channel; "Pedal 5 = Clutch" in the paper's mapping
CAMERA_PEDAL = 5

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

# stream ids: each random schedule / noise source draws from its own (seed, stream, ...) key
_STREAM_PEDAL = 30
_STREAM_PEDAL_STATIC = 70
_STREAM_ADC_NOISE = 140

# columns of the per-press parameter table
_PEAK_N, _ON_BOUNCES, _OFF_BOUNCES, _ON_WINDOW_S, _OFF_WINDOW_S, _RISE_S, _FALL_S, _WOBBLE_PHASE = range(8)
_CONTACT_FORCE_FRACTION = 0.3  # foot impact: force jumps to at least this fraction of the peak
_PRESS_WOBBLE = (0.06, 1.3)  # relative amplitude, Hz of foot-force variation while holding a pedal
_BOUNCE_COUNT_PROBABILITIES = (0.2, 0.4, 0.3, 0.1)  # P(0, 1, 2, 3 contact gaps) at a press edge


@dataclass(frozen=True)
class PedalRest:
    """Per-pedal (n,) rest state: FSR preload resistance (ohm) and a lightly resting foot (N, Hz, rad)."""

    preload_ohm: np.ndarray
    foot_n: np.ndarray
    foot_hz: np.ndarray
    foot_phase_rad: np.ndarray


class FootModel:
    """Pedal presses and FSR readings of one simulated surgeon; t (N,) = seconds since device start."""

    def __init__(self, config: MotionConfig) -> None:
        self.config = config
        self._presses = [
            IntervalSchedule(config.chunk_s, lambda k, p=pedal: self._press_chunk(p, k))
            for pedal in range(len(config.pedal_profiles))
        ]
        self.rest = self._draw_pedal_rest()

    def pressed(self, t: np.ndarray) -> np.ndarray:
        """Press state (N, n_pedals) bool (True while the foot holds the pedal down)."""
        return np.column_stack([self._presses[p].lookup(t)[1] for p in range(self.config.n_pedals)])

    def adc(self, t: np.ndarray) -> np.ndarray:
        """FSR divider readings (N, n_pedals) as 10-bit ADC counts 0..1023 (int32)."""
        t_us = microseconds(t)
        counts = np.empty((t.size, self.config.n_pedals), dtype=np.int32)
        for pedal in range(self.config.n_pedals):
            force = self._press_force(t, pedal) + self._resting_foot_force(t, pedal)
            noise = hash_normal(self.config.seed, _STREAM_ADC_NOISE + pedal, t_us) * self.config.adc_noise_counts
            counts[:, pedal] = self.fsr_counts(force, self.rest.preload_ohm[pedal], noise)
        return counts

    def clutch_intervals(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(starts, ends) s of the clutch presses in chunk k."""
        starts, ends, _ = self._press_chunk(CLUTCH_PEDAL, k)
        return starts, ends

    def fsr_counts(self, force: np.ndarray, rest_ohm: float, noise: np.ndarray) -> np.ndarray:
        """ADC counts (N,) of the divider for force (N,) in N; R_fsr = R1 / F^n in parallel with the preload."""
        cfg = self.config
        conductance = 1.0 / rest_ohm + np.power(force, cfg.fsr_exponent) / cfg.fsr_ohm_at_1n  # siemens
        divider = cfg.fsr_series_ohm * conductance / (1.0 + cfg.fsr_series_ohm * conductance)  # Vout / Vcc
        return np.clip(np.floor(divider * 1024.0 + noise), 0, 1023).astype(np.int32)

    def _press_chunk(self, pedal: int, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(starts, ends, params (M, 8)) of a pedal's presses in chunk k; params columns ``_PEAK_N`` ..."""
        cfg = self.config
        rng = seeded_rng(cfg.seed, _STREAM_PEDAL, pedal, k)
        starts, ends = renewal_events(rng, cfg.pedal_profiles[pedal], k * cfg.chunk_s, (k + 1) * cfg.chunk_s)
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
        held = np.maximum(peak * minimum_jerk(np.clip(ramp, 0.0, 1.0)) * wobble, _CONTACT_FORCE_FRACTION * peak)
        onset_contact = bounce_contact(since_on, params[:, _ON_BOUNCES], params[:, _ON_WINDOW_S])
        release_contact = bounce_contact(until_off, params[:, _OFF_BOUNCES], params[:, _OFF_WINDOW_S])
        force[inside] = np.where(onset_contact & release_contact, held, 0.0)
        return force

    def _draw_pedal_rest(self) -> PedalRest:
        """Per-pedal FSR preload and resting-foot parameters."""
        cfg = self.config
        rng = seeded_rng(cfg.seed, _STREAM_PEDAL_STATIC)
        n = len(cfg.pedal_profiles)
        return PedalRest(
            preload_ohm=np.exp(rng.uniform(*np.log(cfg.fsr_rest_ohm), n)),
            foot_n=rng.uniform(0.0, cfg.resting_foot_max_n, n),
            foot_hz=rng.uniform(0.02, 0.1, n),
            foot_phase_rad=rng.uniform(0.0, 2.0 * np.pi, n),
        )

    def _resting_foot_force(self, t: np.ndarray, pedal: int) -> np.ndarray:
        """Force (N,) in N of a foot resting lightly on a pedal between presses (slowly varying)."""
        rest = self.rest
        angle = 2.0 * np.pi * rest.foot_hz[pedal] * t + rest.foot_phase_rad[pedal]
        return rest.foot_n[pedal] * 0.5 * (1.0 - np.cos(angle))


def bounce_contact(elapsed: np.ndarray, bounces: np.ndarray, window_s: np.ndarray) -> np.ndarray:
    """(N,) bool: foot in contact, ``elapsed`` s after onset (or before release).

    The first ``window_s`` s are split into 2 * bounces + 1 equal slots alternating contact / gap.
    """
    slot = np.floor(elapsed / window_s * (2.0 * bounces + 1.0))
    return (slot % 2.0 == 0.0) | (slot > 2.0 * bounces)
