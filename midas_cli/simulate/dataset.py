"""A simulated dataset: N trials of one platform, one session folder each (run as units of a batch run,
here or on SLURM, by ``dataset_units.py``).

Trial i (1-based) uses subject ``1 + (i - 1) % subjects`` and draws everything from (seed, i), so a trial
is identical whether it is generated alone, in a batch or in another worker process.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from midas_cli.errors import ConfigError
from midas_cli.simulate.style import DEFAULT_DIFFICULTY, check_difficulty
from midas_cli.simulate.trial import TASKS, TrialConfig


def trial_configs(platform: str, trials: int, seed: int, out: Path, subjects: int = 1,
                  latency_ms: float = 40.0, distortion_mm: float = 1.0, max_seconds: float | None = None,
                  difficulty: str = DEFAULT_DIFFICULTY, emht_drift_ppm: float = 0.0) -> list[TrialConfig]:
    """Validated per-trial settings; raises ConfigError naming the bad value."""
    if platform not in TASKS:
        raise ConfigError(f"--platform {platform!r} unknown (expected {' or '.join(TASKS)})")
    checks = [(trials >= 1, f"--trials must be >= 1, got {trials}"), (seed >= 0, f"--seed must be >= 0, got {seed}"),
              (subjects >= 1, f"--subjects must be >= 1, got {subjects}"),
              (0 <= latency_ms <= 500, f"--latency-ms must be in [0, 500], got {latency_ms}"),
              (0 <= distortion_mm <= 50, f"--distortion-mm must be in [0, 50], got {distortion_mm}"),
              (max_seconds is None or max_seconds >= 5, f"--max-seconds must be >= 5, got {max_seconds}"),
              (abs(emht_drift_ppm) <= 1000, f"--emht-drift-ppm must be in [-1000, 1000], got {emht_drift_ppm}")]
    for ok, message in checks:
        if not ok:
            raise ConfigError(message)
    base = TrialConfig(platform, 1, "1", seed, Path(out), latency_ms, distortion_mm, max_seconds,
                       check_difficulty(difficulty), emht_drift_ppm)
    return [replace(base, trial=i, subject=str(1 + (i - 1) % subjects)) for i in range(1, trials + 1)]

