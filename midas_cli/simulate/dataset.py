"""A simulated dataset: N trials of one platform, one session folder each, optionally in parallel.

Trial i (1-based) uses subject ``1 + (i - 1) % subjects`` and draws everything from (seed, i), so a trial
is identical whether it is generated alone, in a batch or in another worker process.
"""

from __future__ import annotations

import logging
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

from midas_cli.errors import ConfigError
from midas_cli.simulate.style import DEFAULT_DIFFICULTY, check_difficulty
from midas_cli.simulate.trial import TASKS, TrialConfig, write_trial

log = logging.getLogger(__name__)


def trial_configs(platform: str, trials: int, seed: int, out: Path, subjects: int = 1,
                  latency_ms: float = 40.0, distortion_mm: float = 1.0, max_seconds: float | None = None,
                  difficulty: str = DEFAULT_DIFFICULTY) -> list[TrialConfig]:
    """Validated per-trial settings; raises ConfigError naming the bad value."""
    if platform not in TASKS:
        raise ConfigError(f"--platform {platform!r} unknown (expected {' or '.join(TASKS)})")
    checks = [(trials >= 1, f"--trials must be >= 1, got {trials}"), (seed >= 0, f"--seed must be >= 0, got {seed}"),
              (subjects >= 1, f"--subjects must be >= 1, got {subjects}"),
              (0 <= latency_ms <= 500, f"--latency-ms must be in [0, 500], got {latency_ms}"),
              (0 <= distortion_mm <= 50, f"--distortion-mm must be in [0, 50], got {distortion_mm}"),
              (max_seconds is None or max_seconds >= 5, f"--max-seconds must be >= 5, got {max_seconds}")]
    for ok, message in checks:
        if not ok:
            raise ConfigError(message)
    base = TrialConfig(platform, 1, "1", seed, Path(out), latency_ms, distortion_mm, max_seconds,
                       check_difficulty(difficulty))
    return [replace(base, trial=i, subject=str(1 + (i - 1) % subjects)) for i in range(1, trials + 1)]


def generate_dataset(configs: list[TrialConfig], jobs: int = 1,
                     progress: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Write every trial (``jobs`` worker processes); ``progress`` is called once per finished trial.
    Returns the per-trial results ({path, duration_s, frames, segments}) in trial order."""
    if jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {jobs}")
    results: dict[int, dict[str, Any]] = {}
    if jobs == 1:
        for config in configs:
            results[config.trial] = _done(write_trial(config), progress)
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            futures = {pool.submit(write_trial, config): config.trial for config in configs}
            for future in as_completed(futures):
                results[futures[future]] = _done(future.result(), progress)
    return [results[c.trial] for c in configs]


def _done(result: dict[str, Any], progress: Callable[[dict[str, Any]], None] | None) -> dict[str, Any]:
    log.info("simulated %s (%.1f s)", result["path"], result["duration_s"])
    if progress is not None:
        progress(result)
    return result
