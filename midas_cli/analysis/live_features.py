"""What a gesture model needs to run live (issue 28): its training run checked for live use, the stream
columns its features read, its frame clock, and each frame's model input built by the training code.

A frame's input: at frame time t (host ns) every needed stream is associated with the three times
t - s, t, t + s by ``analysis.sync.associate`` (align's causal method: the latest sample at or before,
masked when further than 3 nominal periods where the caller gives the rate, else 1 s), the three rows become
an ``AlignedTable`` and ``models.data.modality_features`` (what training runs on an aligned table)
computes the features; the middle row is frame t's. So a velocity is the central difference
training's ``np.gradient`` takes at an interior frame, over s = one frame of the 30 Hz video clock
the training features were computed on (``FEATURE_CLOCK_HZ``; one model frame where the model is
faster): frame t waits for the streams to pass t + s. The features are cast to float32 and
normalised with the checkpoint's normaliser, as training does; a value still missing (a stream
outage) keeps the frame before's (the first frame: the training mean, 0 once normalised).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch

from midas_cli.analysis.sync import associate
from midas_cli.errors import ConfigError, MidasError, SessionError
from midas_cli.models.data import DatasetConfig, Normaliser, modality_features
from midas_cli.models.postprocess import OnlineDecoder, saved_decode_lag, saved_min_segment, saved_switch_scores
from midas_cli.models.train import build_model, load_checkpoint, saved_config, saved_structure
from midas_cli.session.derived import AlignedTable

FEATURE_CLOCK_HZ = 30.0  # the video frame clock training's features (velocities) were computed on
STALE_PERIODS, UNKNOWN_RATE_STALE_NS = 3.0, 1_000_000_000  # align's defaults (AlignOptions, stale_ns_for)
LIVE_PATH = Path("live")  # names the source in feature errors (there is no session folder live)


@dataclass(frozen=True)
class Decoding:
    """A causal run's clean-up as live runs it (``postprocess.OnlineDecoder``): segments at least ``minimum``
    frames, each change of gesture scored by ``switch`` (C, C; None: no order), each frame decided ``lag``
    frames after it. A run from before causal runs were decoded: minimum 0, no order, lag 0, which
    decides every frame as its most probable class (the raw one)."""

    minimum: int = 0
    switch: np.ndarray | None = None
    lag: int = 0

    def decoder(self, n_classes: int) -> OnlineDecoder:
        return OnlineDecoder(n_classes, self.minimum, self.switch, self.lag)

    def offline(self, log_probs: np.ndarray) -> list[int]:
        """The decoded labels of a whole (C, T) sequence, as live decides them frame by frame (one step a
        frame, then ``finish``: ``postprocess.decode_online`` but for a sequence shorter than the minimum)."""
        decoder = self.decoder(log_probs.shape[0])
        return [label for t in range(log_probs.shape[1]) for label in decoder.step(log_probs[:, t])] + decoder.finish()

    def manifest(self) -> dict:
        return {"min_segment_frames": self.minimum, "gesture_order": self.switch is not None, "lag_frames": self.lag}


@dataclass
class LiveRun:
    """A checkpoint that can run live: its model (eval mode, CPU) and how to feed it."""

    run_id: str
    checkpoint_sha256: str
    model_name: str
    model: torch.nn.Module
    classes: tuple[str, ...]
    rate_hz: float
    config: DatasetConfig
    normaliser: Normaliser | None
    columns: list[str]  # every needed aligned column, "<stream>.<column>", in table order
    decoding: Decoding = field(default_factory=Decoding)  # the run's clean-up, as live runs it

    @property
    def streams(self) -> dict[str, tuple[str, ...]]:
        """Stream -> its columns the features read, in ``columns`` order."""
        found: dict[str, list[str]] = {}
        for name in self.columns:
            stream, column = name.split(".", 1)
            found.setdefault(stream, []).append(column)
        return {stream: tuple(cols) for stream, cols in found.items()}


def saved_decoding(saved: dict, n_classes: int) -> Decoding:
    """The ``Decoding`` a run recorded (SessionError for a damaged record)."""
    return Decoding(saved_min_segment(saved), saved_switch_scores(saved.get("switch_scores"), n_classes),
                    saved_decode_lag(saved) or 0)


def load_run(run: Path) -> LiveRun:
    """The training run ``run`` (its folder or its checkpoint.pt) checked for live use; ConfigError naming
    why it cannot run live (no or unreadable checkpoint, not causal, per-trial normalisation, image
    features, the clutch, several model rates)."""
    path = Path(run) / "checkpoint.pt" if Path(run).is_dir() else Path(run)
    if not path.is_file():
        raise ConfigError(f"live model {run}: no checkpoint.pt (give a `midas train gestures` run folder)")
    try:
        saved = load_checkpoint(path)
    except MidasError as exc:
        raise ConfigError(f"live model: {exc}") from None
    try:
        return _live_run(path, saved)
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as exc:  # a damaged or foreign record
        raise ConfigError(f"live model {path}: the checkpoint is not a usable gesture run ({type(exc).__name__}: "
                          f"{exc})") from None
    except SessionError as exc:  # a field checked on the way (e.g. the delay)
        raise ConfigError(f"live model {path}: {exc}") from None


def _live_run(path: Path, saved: dict) -> LiveRun:
    config = DatasetConfig.from_json(saved["dataset_config"])
    _refuse_offline_only(path, config)
    classes = tuple(str(c) for c in saved["classes"])
    dims = {m: len(saved["feature_names"][m]) for m in config.modalities}
    model, model_config = build_model(saved["model"], dims, len(classes), dict(saved["model_options"]),
                                      *saved_structure(saved), recorded=saved_config(saved))
    if "causal" in model_config and not model_config["causal"]:
        raise ConfigError(f"live model {path}: {saved['model']} was not trained with --causal (it looks at frames "
                          "after t); train it with `midas train gestures --causal`")
    model.load_state_dict(saved["state_dict"])
    columns, names = needed_columns(config)
    if names != {m: list(saved["feature_names"][m]) for m in config.modalities}:
        raise ConfigError(f"live model {path}: its features ({saved['feature_names']}) are not the ones this midas "
                          f"builds for {config.features} ({names})")
    normaliser = Normaliser.from_json(saved["normaliser"]) if config.normalise == "train" else None
    rate = _model_rate(path, config, saved)
    decoding = saved_decoding(saved, len(classes))
    if max(decoding.minimum, decoding.lag) >= 3600 * rate:  # what --min-segment and --decode-lag allow
        raise ConfigError(f"live model {path}: its decoding's minimum ({decoding.minimum}) and lag ({decoding.lag}) "
                          f"must be under an hour of frames at {rate:g} Hz")
    return LiveRun(path.parent.name, hashlib.sha256(path.read_bytes()).hexdigest(), str(saved["model"]),
                   model.eval(), classes, rate, config, normaliser, columns, decoding)


def _refuse_offline_only(path: Path, config: DatasetConfig) -> None:
    """ConfigError for what only works on a whole recorded session."""
    why = {"the image modality (features extracted from the finished video)": "image" in config.modalities,
           "--normalise trial (each trial scaled by its whole recording)": config.normalise == "trial",
           "--exclude-clutch": config.exclude_clutch, "the clutch feature set": "clutch" in config.features}
    found = [reason for reason, applies in why.items() if applies]
    if found:
        raise ConfigError(f"live model {path}: trained with {', '.join(found)}, which cannot run live")


def _model_rate(path: Path, config: DatasetConfig, saved: dict) -> float:
    rates = {float(t["rate_hz"]) for t in saved["trials"]}
    rate = config.rate_hz or (rates.pop() if len(rates) == 1 else None)
    if rate is None or not 0 < rate <= 1000:
        raise ConfigError(f"live model {path}: no single model rate (trials at {sorted(rates)} Hz)")
    return float(rate)


class _ColumnSpy(AlignedTable):
    """A three-row aligned table that has every column (ones) and remembers which were read."""

    def __init__(self) -> None:
        super().__init__(np.arange(3), np.arange(3), [], np.zeros((3, 0)))
        self.read: list[str] = []

    def has(self, name: str) -> bool:
        return True

    def column(self, name: str) -> np.ndarray:
        if name not in self.read:
            self.read.append(name)
        return np.ones(3)


def needed_columns(config: DatasetConfig) -> tuple[list[str], dict[str, list[str]]]:
    """The aligned columns the features of ``config`` read ("<stream>.<column>") and the feature names per
    modality, found by running the training code on a table that has every column."""
    spy = _ColumnSpy()
    names = {}
    with np.errstate(all="ignore"):
        for modality in config.modalities:
            names[modality] = modality_features(LIVE_PATH, spy, np.array([-1.0, 0.0, 1.0]), modality, config, [])[1]
    undotted = [n for n in spy.read if "." not in n]
    if undotted:
        raise ConfigError(f"the features read {', '.join(undotted)}, which no single stream gives")
    return spy.read, names


def stale_ns(rate_hz: float | None) -> int:
    """How far a sample may be from a frame and still count (align: 3 nominal periods; 1 s unknown)."""
    return int(STALE_PERIODS * 1e9 / rate_hz) if rate_hz else UNKNOWN_RATE_STALE_NS


def feature_step_ns(rate_hz: float) -> int:
    """s: the spacing (ns) of the three rows a frame's features are computed from."""
    return int(round(1e9 / (rate_hz * max(1, round(FEATURE_CLOCK_HZ / rate_hz)))))


class FrameClock:
    """Frame k at floor(k / rate) s in host ns (exact integer arithmetic: frame times are multiples of the
    period, the same whichever process computes them)."""

    def __init__(self, rate_hz: float) -> None:
        self.period = Fraction(10 ** 9) / Fraction(rate_hz).limit_denominator(10 ** 6)

    def time(self, k: int) -> int:
        return int(k * self.period.numerator // self.period.denominator)

    def first_at_or_after(self, t_ns: int) -> int:
        """The index of the first frame at or after ``t_ns``: ceil(t / period) (then k x period >= t, so its
        floor, an integer, is too; and (k - 1) x period < t)."""
        return int(-(-t_ns * self.period.denominator // self.period.numerator))


def associated(sample_ns: np.ndarray, values: np.ndarray, times_ns: np.ndarray, stale: int) -> np.ndarray:
    """(len(times_ns), C) values of a stream (samples ``sample_ns`` (M,) ascending, ``values`` (M, C)) at
    ``times_ns`` as align associates them (causal), NaN where masked."""
    idx, valid, _ = associate(sample_ns, times_ns, "causal", stale)
    chosen = values[idx] if len(sample_ns) else np.full((len(times_ns), values.shape[1]), np.nan)
    return np.where(valid[:, None], chosen, np.nan)


class FrameInputs:
    """Frame t's model input (D,) float32 from its three associated rows; keeps the last input to fill
    a value still missing. One instance per sequence of frames, fed in order."""

    def __init__(self, live: LiveRun) -> None:
        self.live = live
        self.step_ns = feature_step_ns(live.rate_hz)
        self.times_s = np.array([-self.step_ns, 0, self.step_ns]) / 1e9
        self.previous: np.ndarray | None = None

    def __call__(self, t_ns: int, rows: np.ndarray) -> np.ndarray:
        """``rows`` (3, len(live.columns)): the columns at t - s, t, t + s."""
        table = AlignedTable(np.arange(3), t_ns + np.array([-self.step_ns, 0, self.step_ns]), self.live.columns, rows)
        blocks = [modality_features(LIVE_PATH, table, self.times_s, m, self.live.config, [])[0][1]
                  for m in self.live.config.modalities]
        x = np.concatenate(blocks).astype(np.float32)
        x = self.live.normaliser.apply(x) if self.live.normaliser is not None else x
        missing = ~np.isfinite(x)
        if missing.any():
            x[missing] = self.previous[missing] if self.previous is not None else 0.0
        self.previous = x
        return x
