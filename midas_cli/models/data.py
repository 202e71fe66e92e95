"""Dataset building for gesture recognition: aligned sessions -> simple arrays per trial.

A separate step from training (the loop never parses session files). Per session it reads
``derived/aligned.npz`` (``midas align``; columns ``<stream>.<column>`` on the video frame clock, plus
``clutch``), the frame labels ``labels/<label_set>.csv`` (frame = video ``seq``) and, for the ``image``
modality, ``derived/<image_features>.npz`` (``frame`` (N,), ``features`` (N, D)).

Feature sets per modality (``pos``, ``ori``, ``vel``, ``angvel``, ``grasper``, ``clutch``), the sides and
the rotation representation: see ``models/features.py``.

``clutch`` adds the clutch state (aligned ``clutch`` column) as one feature. A feature set a modality
does not have (HandKP orientation) is skipped and listed in ``GestureDataset.skipped``. Missing values
(HandKP misses, stream outages) are filled by linear interpolation over time per column (edges: the
nearest value; a column with no value at all: 0) -- documented, never silent: the fraction filled is
kept per modality in ``Trial.filled``.

Resampling keeps the first frame of each 1/rate bin (Raven-II 30 -> 10 Hz in the paper, da Vinci
native 30 Hz). ``exclude_clutch`` drops frames with the clutch pressed (before training AND
inference, as in the paper's appendix B). Frames without a label are kept inside a trial as class -1
(ignored by losses and metrics) and trimmed at its ends. A session without the label set, or with no
labelled frame left, is skipped with a warning and listed in ``GestureDataset.skipped_sessions``; only
when no session remains is that an error. Normalisation (``normalise``, applied in ``train.py``):
``train`` (default) = per-feature z-score fitted on the training split only, so test data never shape
it and a test trial is scaled like the trials the model learned from; ``trial`` = each trial scaled
by its own mean and std (removes per-subject/per-setup offsets, e.g. where the robot's base frame
sits, at the price of using a whole test trial's statistics); ``none``.
"""

from __future__ import annotations

import hashlib
import logging
import zipfile
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from midas_cli.errors import ConfigError, SessionError
from midas_cli.models.features import SIDES, clutch, feature_block
from midas_cli.session.derived import AlignedTable, read_aligned
from midas_cli.session.labels import list_label_sets, read_frame_labels
from midas_cli.session.reader import Session

log = logging.getLogger(__name__)

MODALITIES = ("emht", "handkp", "mtm", "psm", "image")
FEATURE_SETS = ("pos", "ori", "vel", "angvel", "grasper", "clutch")
ROTATIONS = ("matrix", "quat")
NORMALISATIONS = ("train", "trial", "none")
# What a checkpoint written before these options existed was built with.
LEGACY_CONFIG = {"sides": ("left", "right"), "rotation": "quat", "normalise": "train"}
PLATFORM_RATE_HZ = {"raven-ii": 10.0}  # the paper's resampling
# Robot-arm kinematics alone (JIGSAWS-style: mtm/psm) at 10 Hz, as the kinematics-only TCN literature
# downsamples; chosen on the JIGSAWS development tasks (README, "Defaults and why"). Everything else (the
# EmHT, HandKP, image features: the paper's inputs) keeps the aligned 30 Hz.
KINEMATICS_RATE_HZ = 10.0
KINEMATICS = {"mtm", "psm"}
DEFAULT_RATE_HZ = 30.0
AUTO = "auto"
# ``--modalities auto`` / ``--features auto``: the EmHT where every session has it (MiDAS sessions: the
# paper's input, with the paper's pos, ori, vel), otherwise the robot arms every session has (JIGSAWS-
# style kinematics: mtm and psm, with position, velocity, angular velocity and the grasper angle). Not the
# orientation itself: how each surgeon holds the tools sits in it as an offset per user (JIGSAWS Needle
# Passing user D), and the models read it as a gesture; how the orientation changes (angvel) is kept.
# Chosen on the JIGSAWS development tasks (README, "Defaults and why").
ROBOT_FEATURES = ("pos", "vel", "angvel", "grasper")
AUTO_CHOICES = ((("emht",), ("pos", "ori", "vel")), (("mtm", "psm"), ROBOT_FEATURES), (("psm",), ROBOT_FEATURES),
                (("mtm",), ROBOT_FEATURES))


@dataclass(frozen=True)
class DatasetConfig:
    """What to build: modalities and feature sets, clutch exclusion, rate (None = platform default),
    which sides (arms / hands), the robot rotation representation and the normalisation."""

    modalities: tuple[str, ...]
    features: tuple[str, ...] = ("pos", "ori", "vel")
    exclude_clutch: bool = False
    rate_hz: float | None = None
    label_set: str = "gestures"
    image_features: str = "image_features"
    sides: tuple[str, ...] = SIDES
    rotation: str = "matrix"
    normalise: str = "train"

    def __post_init__(self) -> None:
        object.__setattr__(self, "modalities", tuple(self.modalities))
        object.__setattr__(self, "features", tuple(self.features))
        sides = tuple(self.sides)
        object.__setattr__(self, "sides", tuple(s for s in SIDES if s in sides))  # canonical order
        if not sides or len(sides) != len(set(sides)) or any(s not in SIDES for s in sides):
            raise ConfigError(f"sides must be left, right or both, got {','.join(sides)!r}")
        if self.rotation not in ROTATIONS:
            raise ConfigError(f"rotation must be one of {', '.join(ROTATIONS)}, got {self.rotation!r}")
        if self.normalise not in NORMALISATIONS:
            raise ConfigError(f"normalise must be one of {', '.join(NORMALISATIONS)}, got {self.normalise!r}")
        for name, given, known in (("modality", self.modalities, MODALITIES), ("feature set", self.features, FEATURE_SETS)):
            if given == (AUTO,):
                continue  # chosen from the sessions by ``resolve_auto``
            bad = [g for g in given if g not in known]
            if bad or not given or len(set(given)) != len(given):
                raise ConfigError(f"{name} list {','.join(given)!r} is invalid (choose distinct values from "
                                  f"{', '.join(known)})")
        if self.rate_hz is not None and not 0 < self.rate_hz <= 1000:
            raise ConfigError(f"rate must be in (0, 1000] Hz, got {self.rate_hz}")

    def to_json(self) -> dict:
        return {**asdict(self), "modalities": list(self.modalities), "features": list(self.features),
                "sides": list(self.sides)}

    @classmethod
    def from_json(cls, data: dict) -> "DatasetConfig":
        """From ``to_json``; keys a run written before they existed take their old meaning."""
        return cls(**{**LEGACY_CONFIG, **data})


@dataclass
class Trial:
    """One session as arrays on its (resampled) frame clock; T frames."""

    name: str
    subject: str
    trial: int
    platform: str
    frames: np.ndarray  # (T,) int64 video frame index of each sample
    inputs: dict[str, np.ndarray]  # modality -> (T, D_m) float32, not normalised
    labels: np.ndarray  # (T,) int64 class index, -1 = unlabelled
    rate_hz: float
    filled: dict[str, float] = field(default_factory=dict)  # modality -> fraction of values filled

    def stacked(self, order: Sequence[str]) -> np.ndarray:
        """(T, sum D_m) float32: the modalities concatenated in ``order``."""
        return np.concatenate([self.inputs[m] for m in order], axis=1)


@dataclass
class GestureDataset:
    trials: list[Trial]
    classes: list[str]
    feature_names: dict[str, list[str]]  # modality -> column names, in input order
    config: DatasetConfig
    skipped: list[str] = field(default_factory=list)  # "modality:feature" pairs that do not exist
    skipped_sessions: dict[str, str] = field(default_factory=dict)  # session path -> why it has no trial

    @property
    def modality_dims(self) -> dict[str, int]:
        return {m: len(self.feature_names[m]) for m in self.config.modalities}

    def trial_index(self, name: str) -> int:
        for i, trial in enumerate(self.trials):
            if trial.name == name:
                return i
        raise SessionError(f"trial {name!r} is not in the dataset (trials: {', '.join(t.name for t in self.trials)})")

    def fingerprint(self) -> str:
        """sha256 over the classes, feature names and every trial's frames, inputs and labels."""
        digest = hashlib.sha256(repr((self.classes, self.feature_names)).encode())
        for trial in self.trials:
            digest.update(trial.name.encode())
            for array in (trial.frames, trial.labels, *(trial.inputs[m] for m in self.config.modalities)):
                digest.update(np.ascontiguousarray(array).tobytes())
        return digest.hexdigest()


@dataclass
class Normaliser:
    """Per-feature mean and std (fitted on training frames only); applied as (x - mean) / std."""

    mean: np.ndarray  # (D,)
    std: np.ndarray  # (D,)

    @classmethod
    def fit(cls, blocks: Sequence[np.ndarray]) -> "Normaliser":
        """Fit on (T_i, D) blocks of training frames."""
        stacked = np.concatenate(blocks, axis=0)
        std = stacked.std(axis=0)
        return cls(stacked.mean(axis=0), np.where(std > 1e-8, std, 1.0))

    def apply(self, x: np.ndarray) -> np.ndarray:
        return ((x - self.mean) / self.std).astype(np.float32)

    def to_json(self) -> dict:
        return {"mean": self.mean.tolist(), "std": self.std.tolist()}

    @classmethod
    def from_json(cls, data: dict) -> "Normaliser":
        return cls(np.asarray(data["mean"], dtype=np.float64), np.asarray(data["std"], dtype=np.float64))


@dataclass
class _RawTrial:
    """One session read at the model rate, labels still strings."""

    session: Session
    frames: np.ndarray  # (T,) int64
    rate_hz: float
    labels: np.ndarray  # (T,) str, '' = unlabelled
    inputs: dict[str, np.ndarray]  # modality -> (T, D_m) float64, filled
    names: dict[str, list[str]]
    filled: dict[str, float]
    skipped: list[str]


def build_dataset(sessions: Sequence[Path], config: DatasetConfig, classes: Sequence[str] | None = None) -> GestureDataset:
    """Arrays per trial for ``sessions`` (each holding aligned data and frame labels).

    ``classes`` fixes the class order (e.g. from a checkpoint); by default the sorted union of labels.
    """
    if not sessions:
        raise ConfigError("no sessions given: pass session folders (or folders holding sessions)")
    labelled = [Path(p) for p in sessions if config.label_set in list_label_sets(p)]
    unlabelled = [str(p) for p in sessions if Path(p) not in labelled]
    if not labelled:
        raise SessionError(f"none of the {len(sessions)} sessions has label set {config.label_set!r} "
                           f"(labels/{config.label_set}.csv): import labels first "
                           "(`midas labels import-via|import-transcription`)")
    config = resolve_auto(config, labelled)
    if unlabelled:
        log.warning("%d of %d sessions skipped: no label set %r: %s", len(unlabelled), len(sessions),
                    config.label_set, ", ".join(unlabelled))
    raws = [_read_session(p, config) for p in labelled]
    seen = sorted({label for raw in raws for label in raw.labels.tolist()} - {""})
    names = seen if classes is None else list(classes)
    unknown = sorted(set(seen) - set(names))
    if unknown:
        raise SessionError(f"labels {', '.join(unknown)} are not among the classes {', '.join(names)}")
    for raw in raws[1:]:
        if raw.names != raws[0].names:
            raise SessionError(f"{raw.session.path}: its feature columns differ from {raws[0].session.path}; "
                               "align every session with the same midas version and devices")
    index = {name: i for i, name in enumerate(names)}
    encoded = [(raw, _to_trial(raw, index)) for raw in raws]
    trials = [t for _, t in encoded if len(t.labels)]
    if not trials:
        raise SessionError("no session has labelled frames after resampling and clutch exclusion")
    empty = [str(raw.session.path) for raw, t in encoded if not len(t.labels)]
    if empty:
        log.warning("%d sessions skipped: no labelled frame after resampling and clutch exclusion: %s",
                    len(empty), ", ".join(empty))
    skipped = sorted({s for raw in raws for s in raw.skipped})
    if skipped:
        log.info("feature sets not available and skipped: %s", ", ".join(skipped))
    return GestureDataset(trials, names, raws[0].names, config, skipped,
                          {**{p: f"no label set {config.label_set!r}" for p in unlabelled},
                           **{p: "no labelled frame after resampling and clutch exclusion" for p in empty}})


def resolve_auto(config: DatasetConfig, sessions: Sequence[Path]) -> DatasetConfig:
    """``config`` with ``auto`` modalities / features replaced by the first of ``AUTO_CHOICES`` whose
    streams every session's aligned table holds; ConfigError naming what they have when none fits."""
    if AUTO not in (config.modalities + config.features):
        return config
    held = [{column.split(".", 1)[0] for column in read_aligned(p).columns} for p in sessions]
    common = set.intersection(*held) if held else set()
    for modalities, features in AUTO_CHOICES:
        if (config.modalities != (AUTO,) and modalities != config.modalities) or not set(modalities) <= common:
            continue
        return replace(config, modalities=modalities if config.modalities == (AUTO,) else config.modalities,
                       features=features if config.features == (AUTO,) else config.features)
    if config.modalities != (AUTO,):  # modalities given, features auto: the sets of the first choice that fits
        return replace(config, features=("pos", "ori", "vel"))
    raise ConfigError(f"--modalities auto: the sessions have no kinematic stream in common (emht, or mtm/psm); "
                      f"common streams: {', '.join(sorted(common)) or 'none'}: name --modalities")


def _read_session(path: Path, config: DatasetConfig) -> _RawTrial:
    session = Session.open(path)
    table = read_aligned(path)
    rows, rate_hz = _kept_rows(table, session, config)
    labels = _frame_labels(path, table.frame[rows], config.label_set)
    times_s = table.times_s()
    inputs, names, filled, skipped = {}, {}, {}, []
    for modality in config.modalities:
        values, cols = modality_features(path, table, times_s, modality, config, skipped)
        if not cols:
            raise ConfigError(f"{path}: modality {modality!r} has none of the feature sets {','.join(config.features)}")
        filled[modality] = float(np.isnan(values[rows]).mean())
        inputs[modality], names[modality] = _fill_missing(values)[rows], cols
    return _RawTrial(session, table.frame[rows].astype(np.int64), rate_hz, labels, inputs, names, filled, skipped)


def _to_trial(raw: _RawTrial, index: dict[str, int]) -> Trial:
    """Encode labels and trim unlabelled frames at both ends."""
    y = np.array([index[label] if label else -1 for label in raw.labels.tolist()], dtype=np.int64)
    labelled = np.flatnonzero(y >= 0)
    keep = slice(labelled[0], labelled[-1] + 1) if len(labelled) else slice(0, 0)
    meta = raw.session.metadata
    return Trial(raw.session.manifest["session_id"], str(meta["subject"]), int(meta["trial"]),
                 str(meta.get("platform", "")), raw.frames[keep],
                 {m: v[keep].astype(np.float32) for m, v in raw.inputs.items()}, y[keep], raw.rate_hz, raw.filled)


def _kept_rows(table: AlignedTable, session: Session, config: DatasetConfig) -> tuple[np.ndarray, float]:
    """Row indices after resampling (first frame of each 1/rate bin) and clutch exclusion; the rate."""
    if len(table.frame) == 0:
        raise SessionError(f"{session.path}: the aligned table has no frames")
    platform = str(session.metadata.get("platform", ""))
    rate = config.rate_hz or default_rate(platform, config.modalities)
    t = table.t_host_ns - table.t_host_ns[0]
    bins = np.floor(t * rate / 1e9 + 1e-3).astype(np.int64)  # tolerance: frame times rounded to ns
    rows = np.flatnonzero(np.r_[True, np.diff(bins) > 0])
    if config.exclude_clutch:
        pressed = clutch(table, session.path)
        rows = rows[~(pressed[rows] > 0.5)]
    return rows, float(rate)


def default_rate(platform: str, modalities: Sequence[str]) -> float:
    """The model rate when ``--model-rate`` is not given: the platform's (Raven-II 10 Hz, the paper's),
    else 10 Hz for robot-arm kinematics alone, else 30 Hz."""
    if platform in PLATFORM_RATE_HZ:
        return PLATFORM_RATE_HZ[platform]
    return KINEMATICS_RATE_HZ if set(modalities) <= KINEMATICS else DEFAULT_RATE_HZ


def _frame_labels(path: Path, frames: np.ndarray, label_set: str) -> np.ndarray:
    """(T,) label strings of ``frames`` (video frame indices); '' where the label set has none."""
    labels = read_frame_labels(path, label_set)
    lookup = dict(zip(labels.frames.tolist(), labels.labels.tolist()))
    return np.array([lookup.get(f, "") for f in frames.tolist()], dtype=object)


def modality_features(path: Path, table: AlignedTable, times_s: np.ndarray, modality: str,
                      config: DatasetConfig, skipped: list[str]) -> tuple[np.ndarray, list[str]]:
    """(N, D) float64 with NaN = missing, and the D names, for one modality at the full frame rate."""
    if modality == "image":
        return _image_features(path, table.frame, config.image_features)
    blocks, names = [], []
    for feature in config.features:
        block = feature_block(table, times_s, modality, feature, path, config.sides, config.rotation)
        if block is None:
            skipped.append(f"{modality}:{feature}")
            continue
        blocks.append(block[0])
        names += block[1]
    return (np.concatenate(blocks, axis=1) if blocks else np.zeros((len(table.frame), 0))), names


def _image_features(path: Path, frames: np.ndarray, name: str) -> tuple[np.ndarray, list[str]]:
    """(N, D) image features at ``frames`` (NaN where the NPZ has no row for a frame)."""
    npz = Path(path) / "derived" / f"{name}.npz"
    if not npz.is_file():
        raise SessionError(f"{path} has no derived/{name}.npz: run `midas extract image-features` on its video first")
    try:
        with np.load(npz, allow_pickle=False) as data:
            feature_frames, features = data["frame"].astype(np.int64), data["features"].astype(np.float64)
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:  # damaged or not an npz at all
        raise SessionError(f"cannot read {npz}: {exc} (re-run `midas extract image-features`)") from exc
    out = np.full((len(frames), features.shape[1]), np.nan)
    pos = np.searchsorted(feature_frames, frames)
    ok = pos < len(feature_frames)
    ok[ok] = feature_frames[pos[ok]] == frames[ok]
    out[ok] = features[pos[ok]]
    return out, [f"image.{i}" for i in range(features.shape[1])]


def _fill_missing(values: np.ndarray) -> np.ndarray:
    """Linear interpolation over rows per column; edges take the nearest value; empty columns 0."""
    out = values.copy()
    rows = np.arange(len(values))
    for j in range(values.shape[1]):
        ok = np.isfinite(values[:, j])
        if ok.all():
            continue
        out[:, j] = np.interp(rows, rows[ok], values[ok, j]) if ok.any() else 0.0
    return out
