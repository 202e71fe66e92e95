"""Deterministic randomness of the synthetic world: seeded generators, counter-based hash noise and
banks of sinusoids.

Every schedule draws from its own generator ``seeded_rng(seed, stream, ...)``; per-sample noise is a
counter-based hash of ``(seed, stream, t rounded to microseconds)``, so evaluating a time range in one
call or in many small batches gives bit-identical values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def seeded_rng(seed: int, *key: int) -> np.random.Generator:
    """A generator that depends only on (seed, key...)."""
    return np.random.default_rng(np.random.SeedSequence([seed, *key]))


_GOLDEN_GAMMA = np.uint64(0x9E3779B97F4A7C15)


def splitmix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser: a bijective avalanche hash of uint64 values (wrapping arithmetic)."""
    with np.errstate(over="ignore"):
        z = x + _GOLDEN_GAMMA
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def hash_uniform(seed: int, stream: int, t_us: np.ndarray) -> np.ndarray:
    """Uniform (0, 1) per sample, a pure function of (seed, stream, t in integer microseconds)."""
    key = splitmix64(np.array([(seed * 0x100000001B3 + stream) % 2**64], dtype=np.uint64))
    z = splitmix64(t_us ^ splitmix64(key))
    return ((z >> np.uint64(11)).astype(np.float64) + 0.5) * 2.0**-53


def hash_normal(seed: int, stream: int, t_us: np.ndarray) -> np.ndarray:
    """Standard normal per sample (Box-Muller over two hashed uniforms)."""
    radius = np.sqrt(-2.0 * np.log(hash_uniform(seed, 2 * stream, t_us)))
    return radius * np.cos(2.0 * np.pi * hash_uniform(seed, 2 * stream + 1, t_us))


def microseconds(t: np.ndarray) -> np.ndarray:
    """Sample times (s) as integer microseconds, the key of every per-sample noise value."""
    return np.rint(t * 1e6).astype(np.uint64)


@dataclass(frozen=True)
class SinusoidBank:
    """Sum of sinusoids per dimension: frequencies_hz, amplitudes, phases_rad all (D, C)."""

    frequencies_hz: np.ndarray
    amplitudes: np.ndarray
    phases_rad: np.ndarray

    @classmethod
    def draw(cls, rng: np.random.Generator, hz: tuple[float, float], amplitudes: np.ndarray) -> SinusoidBank:
        """Random frequencies in ``hz`` and random phases for the given amplitudes (D, C)."""
        frequencies = rng.uniform(hz[0], hz[1], amplitudes.shape)
        return cls(frequencies, amplitudes, rng.uniform(0.0, 2.0 * np.pi, amplitudes.shape))

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """Values (N, D) at t (N,) s."""
        angle = 2.0 * np.pi * self.frequencies_hz * t[:, None, None] + self.phases_rad
        return (self.amplitudes * np.sin(angle)).sum(axis=-1)
