"""Training and evaluation runs for gesture recognition; a run is a self-describing folder.

``RUN_DIR/``
  ``run.json``        dataset + training + model configuration, split, data fingerprint, code version,
                      classes, feature names, normaliser, recipe, per-epoch history, skipped feature sets
                      and skipped sessions (no labels)
  ``metrics.json``    test (and validation) metrics: summary, per-class report, confusion matrix
  ``checkpoint.pt``   weights + everything above needed to rebuild and re-evaluate the model, plain
                      types only, so ``torch.load(path, weights_only=True)`` reads it
  ``predictions/<trial>.csv``  frame, truth, prediction of every test frame
  ``plots/confusion.png``, ``plots/<trial>.png``  (truth / prediction ribbons)

The loop: build arrays (models/data.py) -> split (models/splits.py) -> normalise (default: fitted on the
training units) -> train with the model's recipe (models/registry.py: epochs, batch size, lr, which weights
are kept; resolved in ``run.json`` ``recipe``) -> predict the test units -> metrics. Deterministic on CPU
for a given ``seed`` (weights, batch order and dropout come from seeded generators). A checkpoint rebuilds
the network it trained from its recorded config (``build_model`` ``recorded``), whatever the defaults now.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from midas_cli.errors import ConfigError, SessionError
from midas_cli.models import metrics as M
from midas_cli.models import postprocess
from midas_cli.models.augment import ColumnShift, check_sets, input_shift
from midas_cli.models.averaging import WeightAverage
from midas_cli.models.data import DatasetConfig, GestureDataset, Normaliser, build_dataset
from midas_cli.models.ensemble import Ensemble, each_member, member_configs, member_records
from midas_cli.models.predict import frame_accuracy, predict, predict_log_probs
from midas_cli.models.provenance import code_version
from midas_cli.models.registry import MODELS, model_entry
from midas_cli.models.run_files import run_folder, write_run
from midas_cli.models.sequences import Sequences, epoch_inputs, fit_normaliser, padded_batches, sequences
from midas_cli.models.splits import PARTS, Split, instances, make_split
from midas_cli.models.torch_io import load_weights_only

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "midas-gesture-run/1"
SELECTIONS = ("last", "best-val", "average")  # average: models/averaging.py
RECIPES = {name: asdict(entry.recipe) for name, entry in MODELS.items()}  # each model's recipe, as run.json has it


@dataclass
class TrainConfig:
    model: str = "ensemble"  # the default (README, "Defaults and why")
    split: str = "gesture"
    fold: int = 0
    validation: str = "none"  # group splits: none (fixed epochs, last epoch) or inner (models/splits.py)
    epochs: int | None = None  # None (here and below) = the model's recipe (models/registry.py)
    batch_size: int | None = None
    lr: float | None = None
    selection: str | None = None  # "last" epoch's weights, the "best-val" epoch's, or the second half's "average"
    weight_decay: float = 0.0
    seed: int = 0
    device: str = "cpu"
    shuffle_labels: bool = False  # control: permute the classes of the training gesture instances
    model_options: dict = field(default_factory=dict)  # overrides of the model's config dataclass
    causal: bool = False  # sequence models see frames <= t only (per-frame baselines always do)
    min_segment: str = "none"  # predicted segments shorter than this merged away (models/postprocess.py)
    grammar: str = "none"  # weight of the training gesture order in the offline clean-up (postprocess.decode)
    curve_every: int = 0  # > 0: the test split scored every so many epochs into the history (learning curve)
    delay_s: float = 0.0  # causal: frame t labelled from the frames up to t + delay_s (models/mstcn.py look_ahead)
    decode_lag_s: float = 0.0  # causal: the clean-up decides frame t this much later, as live (postprocess.decode_online)
    augment_shift: float | None = None  # training inputs' columns shifted by N(0, (this x their sd)^2) (models/augment.py)
    augment_features: str | None = None  # which columns the shift moves: pos, ori or pos,ori

    def __post_init__(self) -> None:
        model_entry(self.model)  # ConfigError for an unknown model
        postprocess.check(self.min_segment)
        postprocess.check_weight(self.grammar)
        postprocess.check_lag(self.decode_lag_s, self.causal)
        if self.curve_every < 0:
            raise ConfigError(f"--curve-every must be >= 0 epochs, got {self.curve_every}")
        if self.curve_every and self.model == "ensemble":
            raise ConfigError("--curve-every scores one network as it trains; an ensemble's members train one after "
                              "another: take the curves of its models alone")
        if not 0.0 <= self.delay_s < float("inf"):
            raise ConfigError(f"--delay must be >= 0 seconds, got {self.delay_s}")
        if self.delay_s and not self.causal:
            raise ConfigError("--delay is for --causal models (a model that is not causal sees every later frame)")
        if self.augment_shift is not None and not 0.0 <= self.augment_shift < float("inf"):
            raise ConfigError(f"--augment-shift must be >= 0 (standard deviations), got {self.augment_shift}")
        if self.augment_features is not None:
            check_sets(self.augment_features)
        if (self.epochs is not None and self.epochs < 0) or (self.batch_size is not None and self.batch_size < 1):
            raise ConfigError(f"epochs must be >= 0 and batch size >= 1, got {self.epochs}, {self.batch_size}")
        if self.selection is not None and self.selection not in SELECTIONS:
            raise ConfigError(f"--weights must be one of {', '.join(SELECTIONS)}, got {self.selection!r}")
        if self.device not in ("cpu", "cuda"):
            raise ConfigError(f"--device must be cpu or cuda, got {self.device!r}")

    def resolved(self) -> "TrainConfig":
        """This config with every None taken from the model's recipe (what a run records)."""
        recipe = RECIPES[self.model]
        return replace(self, **{k: recipe[k] for k in recipe if getattr(self, k) is None})


@dataclass
class RunResult:
    out_dir: Path
    metrics: dict
    history: list[dict]


ProgressFn = Callable[[int, int, dict], None]


def train_run(sessions: Sequence[Path], data_config: DatasetConfig, config: TrainConfig, out_dir: Path,
              progress: ProgressFn | None = None) -> RunResult:
    """Build the data, train, evaluate on the test units and write the run folder."""
    with run_folder(out_dir) as out_dir:
        config = config.resolved()
        device = torch_device(config.device)
        dataset = build_dataset(sessions, data_config)
        fold = prepare_fold(dataset, config)
        model, model_cfg = seeded_model(dataset, config)
        model.to(device)
        history = fit(model, fold.parts["train"], fold.parts["val"], config, device, progress,
                      curve=fold.parts["test"] if config.curve_every else None, augment=fold.augment)
        return finish_run(out_dir, dataset, fold, config, model, model_cfg, history, device)


@dataclass
class PreparedFold:
    """One run's split of the data, its normalised parts (train, val, test) and the training inputs'
    augmentation (None: none)."""

    split: Split
    normaliser: Normaliser | None
    parts: dict[str, Sequences]
    augment: ColumnShift | None = None


def prepare_fold(dataset: GestureDataset, config: TrainConfig) -> PreparedFold:
    """The split of ``config`` (seed, fold, validation), the training-set normaliser and the parts as
    arrays (training labels shuffled for the control run)."""
    split = make_split(dataset, config.split, config.seed, config.fold, config.validation)
    order = list(dataset.config.modalities)
    normaliser = fit_normaliser(dataset, split.units["train"], order)
    parts = {part: sequences(dataset, split.units[part], normaliser, order) for part in PARTS}
    if not parts["train"].units or not parts["test"].units:
        raise SessionError(f"split {split.kind} left no training or no test units: more labelled data needed")
    if config.shuffle_labels:
        parts["train"].y = shuffled_instance_labels(parts["train"].y, config.seed)
    names = [name for modality in order for name in dataset.feature_names[modality]]
    recipe = config.resolved()
    augment = input_shift(recipe.augment_shift or 0.0, recipe.augment_features or "pos", names, parts["train"].x,
                          recipe.seed)
    if config.augment_shift and augment is None:  # asked for (a recipe's shift is quietly nothing here)
        log.warning("--augment-shift %g: the features have no %s column, nothing is shifted", config.augment_shift,
                    recipe.augment_features)
    return PreparedFold(split, normaliser, parts, augment)


def seeded_model(dataset: GestureDataset, config: TrainConfig) -> tuple[torch.nn.Module, dict]:
    """The untrained network of ``config`` (on the CPU), its weights drawn after ``torch.manual_seed(seed)``."""
    torch.manual_seed(config.seed)
    delay = delay_frames(config.delay_s, dataset.trials[0].rate_hz)
    if config.delay_s and not delay:
        log.warning("--delay %g s is less than half a frame at %g Hz: no delay", config.delay_s, dataset.trials[0].rate_hz)
    return build_model(config.model, dataset.modality_dims, len(dataset.classes), config.model_options, config.causal,
                       delay)


def delay_frames(delay_s: float, rate_hz: float) -> int:
    """``--delay`` in frames of the model's rate (rounded)."""
    return int(round(delay_s * rate_hz))


def finish_run(out_dir: Path, dataset: GestureDataset, fold: PreparedFold, config: TrainConfig,
               model: torch.nn.Module, model_cfg: dict, history: list[dict], device: torch.device) -> RunResult:
    """Evaluate the trained ``model`` on the test (and validation) units and write the run folder."""
    rate = dataset.trials[0].rate_hz
    minimum = postprocess.min_frames(config.min_segment, fold.parts["train"].y, rate)
    weight = postprocess.grammar_weight(config.grammar, rate)
    switch = postprocess.switch_scores(fold.parts["train"].y, len(dataset.classes), weight)
    lag = delay_frames(config.decode_lag_s, rate) if config.causal else None  # a causal run: decoded as live
    result = {"test": _evaluate(model, fold.parts["test"], dataset.classes, device, minimum, switch, lag)}
    if fold.parts["val"].units:
        result["val"] = _evaluate(model, fold.parts["val"], dataset.classes, device, minimum, switch, lag)
    run = {**_run_record(dataset, fold.split, fold.normaliser, config, model_cfg, history), "min_segment_frames": minimum,
           "grammar_weight": weight, "switch_scores": None if switch is None else switch.tolist(),
           "decode_lag_frames": lag}
    write_run(out_dir, run, result, model, dataset, fold.parts["test"], device)
    return RunResult(out_dir, result, history)


def evaluate_checkpoint(sessions: Sequence[Path], checkpoint: Path, out_dir: Path, device_name: str = "cpu") -> RunResult:
    """Re-evaluate a saved model on the test units of its own split (trials found in ``sessions``)."""
    with run_folder(out_dir) as out_dir:
        return _evaluate_checkpoint(sessions, checkpoint, out_dir, device_name)


def _evaluate_checkpoint(sessions: Sequence[Path], checkpoint: Path, out_dir: Path, device_name: str) -> RunResult:
    device = torch_device(device_name)
    saved = load_checkpoint(checkpoint)
    data_config = DatasetConfig.from_json(saved["dataset_config"])
    dataset = build_dataset(sessions, data_config, classes=saved["classes"])
    if dataset.feature_names != saved["feature_names"]:
        raise SessionError(f"the sessions give features {dataset.modality_dims}, the checkpoint was trained on "
                           f"{ {m: len(v) for m, v in saved['feature_names'].items()} }")
    split = Split.from_json(saved["split"])
    normaliser = Normaliser.from_json(saved["normaliser"]) if data_config.normalise == "train" else None
    test = sequences(dataset, split.units["test"], normaliser, list(data_config.modalities))
    name = saved["model"]
    if name == "transformer" and "refinement_stages" not in saved_config(saved):
        name = "transformer-plain"  # a checkpoint from before the refinement stages existed
    model, _ = build_model(name, dataset.modality_dims, len(dataset.classes), saved["model_options"],
                           *saved_structure(saved), recorded=saved_config(saved))
    model.load_state_dict(saved["state_dict"])
    model.to(device)
    switch = postprocess.saved_switch_scores(saved.get("switch_scores"), len(dataset.classes))
    result = {"test": _evaluate(model, test, dataset.classes, device, postprocess.saved_min_segment(saved), switch,
                                postprocess.saved_decode_lag(saved))}
    run = {**{k: v for k, v in saved.items() if k != "state_dict"}, "evaluated_checkpoint": str(checkpoint),
           "data_fingerprint_now": dataset.fingerprint(), "skipped_sessions_now": dataset.skipped_sessions}
    write_run(out_dir, run, result, model, dataset, test, device, save_checkpoint=False)
    return RunResult(out_dir, result, saved.get("history", []))


DATA_SIZED = ("modality_dims", "n_classes", "in_features")  # config fields a builder takes from the data


def saved_config(saved: dict) -> dict:
    """A saved run's recorded network config (``model_config``; {} for a run from before it was kept)."""
    if isinstance(recorded := saved.get("model_config", {}), dict):
        return recorded
    raise SessionError(f"the checkpoint's model_config must be a mapping, got {type(recorded).__name__}")


def saved_structure(saved: dict) -> tuple[bool, int]:
    """``causal`` and ``delay`` (frames) of a saved run's network (False, 0 for one from before them)."""
    delay = (recorded := saved_config(saved)).get("delay", 0)
    if isinstance(delay, bool) or not isinstance(delay, int) or delay < 0:
        raise SessionError(f"the checkpoint's delay must be a whole number of frames >= 0, got {delay!r}")
    return bool(recorded.get("causal", False)), delay


def build_model(name: str, modality_dims: dict[str, int], n_classes: int, options: dict,
                causal: bool = False, delay: int = 0, recorded: dict | None = None) -> tuple[torch.nn.Module, dict]:
    """The network and its config as a plain dict; ``options`` override config fields; ``causal`` sets the
    config's ``causal`` where the model has one (a per-frame model has none: it is causal as it is), and
    ``delay`` (frames) its ``delay`` (a per-frame model has none either: it labels frame t at t).
    ``recorded``: a saved run's config (``saved_config``; the data-sized fields aside): the network as trained."""
    model_cls, cfg = model_entry(name).build(modality_dims, n_classes)
    options = {**{k: v for k, v in (recorded or {}).items() if k in asdict(cfg) and k not in DATA_SIZED}, **options}
    options = {**options, **({"causal": True} if causal and "causal" in asdict(cfg) else {}),
               **({"delay": int(delay)} if delay and "delay" in asdict(cfg) else {})}
    unknown = set(options) - set(asdict(cfg))
    if unknown:
        raise ConfigError(f"model options {', '.join(sorted(unknown))} do not exist for {name} "
                          f"(known: {', '.join(asdict(cfg))})")
    cfg = type(cfg)(**{**asdict(cfg), **options})
    return model_cls(cfg), asdict(cfg)


def fit(model: torch.nn.Module, train: Sequences, val: Sequences, config: TrainConfig, device: torch.device,
        progress: ProgressFn | None = None, curve: Sequences | None = None,
        augment: ColumnShift | None = None) -> list[dict]:
    """Adam on the training units for ``config.epochs`` (None fields: the model's recipe); keeps the
    last epoch's weights, or with selection "best-val" restores the best validation epoch's, with "average"
    the mean of the second half's (models/averaging.py; the learning curve scores each epoch's own). On CUDA
    the forward pass and loss run in mixed precision (autocast float16, the loss scaled by GradScaler);
    on the CPU everything stays float32. With ``config.curve_every`` > 0, ``curve`` (the test split) is
    scored every that many epochs and after the last (``learning_curve_point``): a learning curve for
    choosing the epochs on development data, never used by training or selection (an evaluation in
    eval mode draws no random numbers: the weights are the same with it or without). ``augment``
    (``prepare_fold``'s) redraws the training inputs' position shifts every epoch. An ``Ensemble`` trains
    its members one after another (``fit_members``)."""
    config = config.resolved()
    if isinstance(model, Ensemble):
        return fit_members(model, train, val, config, device, progress, augment)
    # fused: the same update in one kernel over all parameters (MS-TCN++ step at the defaults: -7 % on the CPU)
    optimiser = torch.optim.Adam(model.parameters(), lr=config.lr, weight_decay=config.weight_decay, fused=True)
    rng = np.random.default_rng(config.seed)
    history, best = [], (-1.0, None)
    mixed = device.type == "cuda"
    scaler = torch.amp.GradScaler("cuda", enabled=mixed)
    average = WeightAverage(config.epochs) if config.selection == "average" else None
    for epoch in range(1, config.epochs + 1):
        model.train()
        losses = []
        for batch in padded_batches(epoch_inputs(train, augment), rng.permutation(len(train.x)), config.batch_size):
            x, y, mask = (t.to(device) for t in batch)
            with torch.autocast(device_type=device.type, dtype=torch.float16, enabled=mixed):
                loss = model.loss(model(x, mask), y, mask)
            optimiser.zero_grad()
            scaler.scale(loss).backward()  # not enabled (CPU): loss.backward() and optimiser.step() as they were
            scaler.step(optimiser)
            scaler.update()
            losses.append(float(loss.detach()))
        val_acc = frame_accuracy(model, val, device) if val.units else None
        history.append({"epoch": epoch, "loss": float(np.mean(losses)), "val_accuracy": val_acc})
        if curve is not None and config.curve_every and (epoch % config.curve_every == 0 or epoch == config.epochs):
            history[-1]["test_curve"] = learning_curve_point(model, curve, device)
        if config.selection == "best-val" and val_acc is not None and val_acc > best[0]:
            best = (val_acc, {k: v.detach().clone() for k, v in model.state_dict().items()})
        if average is not None:
            average.after_epoch(model, epoch)
        if progress:
            progress(epoch, config.epochs, history[-1])
    if best[1] is not None:
        model.load_state_dict(best[1])
    if average is not None:
        average.apply(model)
    return history


def fit_members(model: Ensemble, train: Sequences, val: Sequences, config: TrainConfig, device: torch.device,
                progress: ProgressFn | None = None, augment: ColumnShift | None = None) -> list[dict]:
    """``fit`` for each member of ``model`` in turn (``each_member``)."""
    history: list[dict] = []
    for i, member_config, member_progress in each_member(config, model.cfg.members, progress):
        history += member_records(i, member_config, fit(model.members[i], train, val, member_config, device,
                                                        member_progress, augment=augment))
    return history


def learning_curve_point(model: torch.nn.Module, seqs: Sequences, device: torch.device) -> dict:
    """The raw predictions' (no --min-segment) labelled frames and correct ones (pooled accuracy over
    folds = sum correct / sum frames) and each unit's edit score, in unit order."""
    preds = predict(model, seqs, device)
    labelled = [y != M.IGNORE for y in seqs.y]
    return {"frames": int(sum(int(k.sum()) for k in labelled)),
            "correct": int(sum(int((p[k] == y[k]).sum()) for p, y, k in zip(preds, seqs.y, labelled))),
            "edit": [round(float(M.edit_score(p, y)), 3) for p, y in zip(preds, seqs.y)]}


def shuffled_instance_labels(labels: list[np.ndarray], seed: int) -> list[np.ndarray]:
    """Control: the classes of all training gesture instances permuted (seeded); structure is kept,
    the link between signal and class is broken."""
    found = [(i, cls, a, b) for i, y in enumerate(labels) for cls, a, b in instances(y)]
    permuted = np.random.default_rng(seed + 7919).permutation([cls for _, cls, _, _ in found])
    out = [y.copy() for y in labels]
    for (i, _, a, b), cls in zip(found, permuted):
        out[i][a:b] = cls
    return out


def load_checkpoint(path: Path) -> dict:
    saved = load_weights_only(path, "checkpoint")
    if not isinstance(saved, dict) or saved.get("format") != CHECKPOINT_FORMAT:
        raise SessionError(f"{path} is not a midas gesture checkpoint (expected format {CHECKPOINT_FORMAT})")
    return saved


def _evaluate(model: torch.nn.Module, seqs: Sequences, classes: list[str], device: torch.device,
              min_segment_frames: int = 0, switch: np.ndarray | None = None, lag: int | None = None) -> dict:
    """Metrics of the predictions after the clean-up (``raw``: before it, where there was one; ``lag``:
    decoded as live, ``postprocess.clean_up``)."""
    log_probs = predict_log_probs(model, seqs, device)
    raw = [lp.argmax(axis=0) for lp in log_probs]
    if not min_segment_frames and switch is None:
        return {**M.evaluate(raw, seqs.y, classes), "predictions": raw}
    preds = postprocess.clean_up(log_probs, min_segment_frames, switch, lag)
    return {**M.evaluate(preds, seqs.y, classes), "min_segment_frames": min_segment_frames,
            "grammar": switch is not None, "decode_lag_frames": lag, "raw": M.evaluate(raw, seqs.y, classes)["summary"],
            "predictions": preds}


def _run_record(dataset: GestureDataset, split: Split, normaliser: Normaliser | None, config: TrainConfig,
                model_cfg: dict, history: list[dict]) -> dict:
    return {"format": CHECKPOINT_FORMAT, "model": config.model, "model_config": model_cfg,
            "model_options": dict(config.model_options), "train_config": asdict(config),
            "dataset_config": dataset.config.to_json(), "classes": list(dataset.classes),
            "feature_names": dataset.feature_names, "skipped_features": dataset.skipped,
            "skipped_sessions": dataset.skipped_sessions,
            "trials": [{"name": t.name, "subject": t.subject, "trial": t.trial, "platform": t.platform,
                        "frames": int(len(t.labels)), "rate_hz": t.rate_hz, "filled": t.filled}
                       for t in dataset.trials],
            "split": split.to_json(), "normalise": dataset.config.normalise,
            "normaliser": normaliser.to_json() if normaliser is not None else None,
            "recipe": _recipe_record(config, model_cfg),
            "data_fingerprint": dataset.fingerprint(), "code": code_version(torch.__version__), "history": history}


def _recipe_record(config: TrainConfig, model_cfg: dict) -> dict:
    """The recipe fields of ``config`` as trained (an ensemble's: its own and each member's)."""
    record = {k: getattr(config, k) for k in RECIPES[config.model]}
    if "members" in model_cfg:
        record["members"] = [{"model": c.model, "seed": c.seed, **{k: getattr(c, k) for k in RECIPES[c.model]}}
                             for c in member_configs(config, model_cfg["members"])]
    return record


def torch_device(name: str) -> torch.device:
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--accelerator cuda asked for, but torch sees no CUDA GPU (use --accelerator cpu)")
    if name not in ("cpu", "cuda"):
        raise ConfigError(f"--device must be cpu or cuda, got {name!r}")
    return torch.device(name)
