"""The trakSTAR emulator on a pty as a pytest fixture, and the values it sent (for zero-loss checks)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from midas_cli.devices.pty_emulator import Faults
from midas_cli.devices.trakstar.emulator import EmulatorConfig, TrakstarEmulator


@pytest.fixture
def emulator(tmp_path: Path, request):
    faults = dict(getattr(request, "param", {}))
    seed = faults.pop("seed", 0)
    emu = TrakstarEmulator(EmulatorConfig(seed=seed, link=str(tmp_path / "trakstar"), faults=Faults(**faults))).start()
    yield emu
    emu.stop()


def expected_values(emu: TrakstarEmulator, summary: dict, first_index: int, count: int) -> np.ndarray:
    """The sensor values the emulator sent for stream records ``first_index`` .. + ``count``."""
    times = np.array(summary["stream_t_model_s"][first_index:first_index + count])
    return emu.expected_values(times, summary["range_in"])
