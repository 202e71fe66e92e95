"""The simulated surgeon's gestures: per-gesture durations and the order of gestures in a trial.

The gesture sets themselves (ids, names, order) are the shipped taxonomies of ``midas_cli.labels``
(``peg-transfer``, ``hernia-suturing``); this module adds what a simulation needs on top of them.

Durations (mean +/- std, seconds) and segment counts are the paper's dataset table (Raven-II peg
transfer after DESK, S1-S7; da Vinci Xi hernia suturing, G1-G8). Each duration is drawn from a
log-normal with that mean and std, clipped to [``MIN_DURATION_S``, ``MAX_DURATION_S``].

Order: a first-order Markov chain over gestures.
* Peg transfer: the DESK order S1 -> ... -> S7 per peg with small retry probabilities (configured to
  reproduce the table's counts; ``PEG_TRANSITIONS``); a trial moves three pegs; Idle between pegs.
* Suturing: transitions learned from real sequences (COMPASS/JIGSAWS suturing transcriptions), stored as
  counts in ``midas_cli/data/suturing_transitions.json`` with their provenance and the JIGSAWS -> paper
  label mapping; the knot-tying gestures (G5, G7, G8), absent from JIGSAWS suturing, follow the
  configured "knot block" in the same file.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from midas_cli.errors import ConfigError, SessionError
from midas_cli.labels.taxonomy import Taxonomy, shipped_taxonomy
from midas_cli.labels.transcription import read_transcription

MIN_DURATION_S = 0.5
MAX_DURATION_S = 150.0
IDLE = "Idle"
END = "END"
TRANSITIONS_FILE = "suturing_transitions.json"

# gesture id (names: the taxonomy's file): (samples in the paper's table, mean s, std s)
PEG_TRANSFER_TABLE = {
    "S1": (49, 5.84, 3.66),
    "S2": (50, 6.05, 7.22),
    "S3": (51, 2.83, 1.28),
    "S4": (52, 8.08, 4.04),
    "S5": (50, 9.65, 6.85),
    "S6": (47, 5.87, 2.52),
    "S7": (46, 5.37, 2.74),
    IDLE: (0, 2.0, 1.0),  # between pegs; not in the paper's table
}
SUTURING_TABLE = {
    "G1": (246, 9.30, 9.48),
    "G2": (321, 3.61, 7.63),
    "G3": (328, 7.82, 10.88),
    "G4": (273, 5.72, 6.67),
    "G5": (39, 6.10, 6.56),
    "G6": (233, 13.12, 21.98),
    "G7": (143, 5.07, 3.74),
    "G8": (141, 8.47, 6.88),
}
# DESK order with retries: S2->S1 missed approach, S3->S2 peg slipped, S5->S4 failed exchange,
# S7->S6 re-approach; after placing, the next peg (S1) or a pause (Idle).
PEG_TRANSITIONS = {
    IDLE: {"S1": 1.0},
    "S1": {"S2": 1.0},
    "S2": {"S3": 0.97, "S1": 0.03},
    "S3": {"S4": 0.96, "S2": 0.04},
    "S4": {"S5": 1.0},
    "S5": {"S6": 0.94, "S4": 0.06},
    "S6": {"S7": 1.0},
    "S7": {IDLE: 0.6, "S1": 0.4},
}
PEGS_PER_TRIAL = 3
SUTURING_SEGMENTS_PER_TRIAL = (101.0, 12.0)  # 1,724 segments / 17 trials; spread configured


@dataclass(frozen=True)
class GestureModel:
    """How a simulated surgeon performs a taxonomy's gestures: duration stats and transition matrix,
    indexed in the taxonomy's order."""

    taxonomy: Taxonomy
    mean_s: np.ndarray  # (K,)
    std_s: np.ndarray  # (K,)
    transitions: np.ndarray  # (K, K) row-stochastic, zero diagonal
    start: str

    @property
    def name(self) -> str:
        """The taxonomy's name, as label sets record it."""
        return self.taxonomy.name

    @property
    def labels(self) -> tuple[str, ...]:
        """The gesture ids in the taxonomy's order."""
        return tuple(self.taxonomy.ids)

    def index(self, label: str) -> int:
        return self.labels.index(label)

    def draw_duration(self, rng: np.random.Generator, label: str) -> float:
        """One duration (s): log-normal with the label's mean and std, clipped."""
        k = self.index(label)
        sigma2 = np.log1p((self.std_s[k] / self.mean_s[k]) ** 2)
        value = rng.lognormal(np.log(self.mean_s[k]) - sigma2 / 2, np.sqrt(sigma2))
        return float(np.clip(value, MIN_DURATION_S, MAX_DURATION_S))

    def next_label(self, rng: np.random.Generator, label: str) -> str:
        return self.labels[int(rng.choice(len(self.labels), p=self.transitions[self.index(label)]))]


def _matrix(labels: tuple[str, ...], table: dict[str, dict[str, float]]) -> np.ndarray:
    matrix = np.zeros((len(labels), len(labels)))
    for source, row in table.items():
        for target, p in row.items():
            matrix[labels.index(source), labels.index(target)] += p
    return matrix / matrix.sum(axis=1, keepdims=True)


def _taxonomy_with_stats(name: str, table: dict[str, tuple[int, float, float]]) -> tuple[Taxonomy, np.ndarray]:
    """The shipped taxonomy ``name`` and (K, 2) mean and std seconds of its gestures, in its order;
    ConfigError when the table and the taxonomy name different gestures."""
    taxonomy = shipped_taxonomy(name)
    if set(taxonomy.ids) != set(table):
        raise ConfigError(f"taxonomy {name!r} ({', '.join(taxonomy.ids)}) and the simulation's duration table "
                          f"({', '.join(table)}) name different gestures")
    return taxonomy, np.array([table[k][1:] for k in taxonomy.ids])


def peg_transfer() -> GestureModel:
    taxonomy, stats = _taxonomy_with_stats("peg-transfer", PEG_TRANSFER_TABLE)
    labels = tuple(taxonomy.ids)
    return GestureModel(taxonomy, stats[:, 0], stats[:, 1], _matrix(labels, PEG_TRANSITIONS), IDLE)


def hernia_suturing() -> GestureModel:
    taxonomy, stats = _taxonomy_with_stats("hernia-suturing", SUTURING_TABLE)
    labels = tuple(taxonomy.ids)
    return GestureModel(taxonomy, stats[:, 0], stats[:, 1], suturing_matrix(load_transition_data(), labels), "G1")


def load_transition_data() -> dict:
    """The packaged suturing transition data (learned counts, label mapping, knot block)."""
    text = resources.files("midas_cli.data").joinpath(TRANSITIONS_FILE).read_text(encoding="utf-8")
    return json.loads(text)


def suturing_matrix(data: dict, labels: tuple[str, ...]) -> np.ndarray:
    """(K, K) transition matrix over the paper's labels: learned JIGSAWS counts mapped into the paper's
    taxonomy (self-transitions from merged labels and END dropped), then the knot block: from each
    source in ``knot_block``, its listed probabilities replace that share of the learned row."""
    mapping = data["jigsaws_to_paper"]
    counts = np.zeros((len(labels), len(labels)))
    for source, row in data["learned_counts"].items():
        for target, n in row.items():
            a, b = mapping.get(source), mapping.get(target)
            if a in labels and b in labels and a != b:
                counts[labels.index(a), labels.index(b)] += n
    learned = counts / np.maximum(counts.sum(axis=1, keepdims=True), 1)
    for source, row in data["knot_block"].items():
        share = sum(row.values())
        learned[labels.index(source)] *= 1.0 - share if learned[labels.index(source)].sum() else 0.0
        for target, p in row.items():
            learned[labels.index(source), labels.index(target)] += p
    return learned / learned.sum(axis=1, keepdims=True)


def derive_transition_counts(folder: Path | str) -> dict[str, dict[str, int]]:
    """First-order transition counts between consecutive segments of every ``*.txt`` transcription in
    ``folder`` (lines ``start end label``); the last segment of each file transitions to ``END``."""
    files = sorted(Path(folder).glob("*.txt"))
    if not files:
        raise SessionError(f"{folder} holds no *.txt gesture transcriptions")
    counts: dict[str, dict[str, int]] = {}
    for path in files:
        sequence = [segment.label for segment in read_transcription(path)] + [END]
        for a, b in zip(sequence[:-1], sequence[1:]):
            counts.setdefault(a, {}).setdefault(b, 0)
            counts[a][b] += 1
    return {a: dict(sorted(row.items())) for a, row in sorted(counts.items())}


def gesture_model_for(platform: str) -> GestureModel:
    """The gesture model of a platform's simulated task (raven-ii: peg transfer, davinci-xi: suturing)."""
    if platform == "raven-ii":
        return peg_transfer()
    if platform == "davinci-xi":
        return hernia_suturing()
    raise ConfigError(f"platform {platform!r} unknown (expected raven-ii or davinci-xi)")


def sample_segments(rng: np.random.Generator, model: GestureModel, max_seconds: float | None = None
                    ) -> list[tuple[str, float]]:
    """(label, duration s) of one trial. Peg transfer: until the third peg is placed, then Idle.
    Suturing: a segment count ~ N(101, 12). ``max_seconds`` ends the trial at the first gesture
    boundary past it (short trials for tests)."""
    peg = model.name == "peg-transfer"
    target = PEGS_PER_TRIAL if peg else max(8, int(rng.normal(*SUTURING_SEGMENTS_PER_TRIAL)))
    label, done, elapsed, segments = model.start, 0, 0.0, []
    while True:
        segments.append((label, model.draw_duration(rng, label)))
        elapsed += segments[-1][1]
        done += (label == "S7") if peg else 1
        if done >= target or (max_seconds is not None and elapsed >= max_seconds):
            break
        label = model.next_label(rng, label)
    if peg and segments[-1][0] != IDLE:
        segments.append((IDLE, model.draw_duration(rng, IDLE)))
    return segments
