"""Pedal press states from FSR voltages: per-channel thresholds with hysteresis (pure, stateful).

A channel becomes pressed when its voltage rises to ``press_v`` or above and released when it falls
to ``release_v`` or below; in between it keeps its state, so contact bounce does not chatter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from midas_cli.errors import ConfigError

ADC_FULL_SCALE = 1023
# the paper's table "Mapping between da Vinci console pedals and FPS channels" (a rig without a
# ``pedals`` table uses it)
DAVINCI_PEDALS = {1: "secondary_energy_left", 2: "secondary_energy_right", 3: "primary_energy_left",
                  4: "primary_energy_right", 5: "clutch", 6: "camera", 7: "arm_swap"}
VCC = 5.0


def adc_to_volts(counts: np.ndarray | int) -> np.ndarray | float:
    """10-bit ADC counts referenced to Vcc = 5 V -> volts."""
    return np.asarray(counts) * (VCC / ADC_FULL_SCALE)


@dataclass
class PedalThresholds:
    """Per-channel press/release thresholds in volts (press_v > release_v)."""

    press_v: tuple[float, ...]
    release_v: tuple[float, ...]

    def __post_init__(self) -> None:
        if len(self.press_v) != len(self.release_v):
            raise ConfigError("press and release threshold lists differ in length")
        for i, (on, off) in enumerate(zip(self.press_v, self.release_v), start=1):
            if not 0 < off < on < VCC:
                raise ConfigError(f"pedal channel {i}: need 0 < release ({off} V) < press ({on} V) < {VCC} V")

    @classmethod
    def uniform(cls, channels: int, press_v: float = 1.5, release_v: float = 1.0) -> "PedalThresholds":
        return cls((press_v,) * channels, (release_v,) * channels)


class PedalStateTracker:
    """Feeds voltages sample by sample and returns the debounced press state per channel."""

    def __init__(self, thresholds: PedalThresholds) -> None:
        self._press = np.asarray(thresholds.press_v)
        self._release = np.asarray(thresholds.release_v)
        self._limits = list(zip(self._press.tolist(), self._release.tolist()))
        self._state = [False] * len(self._press)

    @property
    def state(self) -> np.ndarray:
        """Pressed (channels,) bool after the last sample."""
        return np.array(self._state, dtype=bool)

    def update(self, volts: np.ndarray) -> np.ndarray:
        """volts: (channels,) -> pressed (channels,) bool after this sample."""
        state = np.where(volts >= self._press, True, np.where(volts <= self._release, False, self.state))
        self._state = state.tolist()
        return state

    def update_counts(self, counts: "list[int] | tuple[int, ...]") -> list[int]:
        """One sample's ADC counts -> pressed (0/1) per channel: ``update(adc_to_volts(counts))`` in plain
        Python, for a driver that sees one sample per read (850 a second: numpy's per-call cost on
        nine numbers was most of the pedal worker's CPU)."""
        scale = VCC / ADC_FULL_SCALE
        state = self._state
        for i, (press, release) in enumerate(self._limits):
            volts = counts[i] * scale
            if volts >= press:
                state[i] = True
            elif volts <= release:
                state[i] = False
        return [int(s) for s in state]
