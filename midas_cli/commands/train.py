"""`midas train gestures|ablation`: gesture recognition with MS-TCN++ or the MTRSAP-style transformer."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Optional

import typer
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from midas_cli.commands import executor as ex
from midas_cli.commands.common import error_line, out, positive, print_json
from midas_cli.commands.options import (JSON_OPTION, SESSION_TREES_ARG, accelerator_option, keyword_options,
                                       option_group, renamed_option, take_renamed)
from midas_cli.commands.progress import progress_display
from midas_cli.errors import ConfigError
from midas_cli.jobs.options import BatchOptions
from midas_cli.models.registry import ENTRIES, model_help
from midas_cli.session.reader import find_sessions

if TYPE_CHECKING:
    from midas_cli.models.train import TrainConfig

# midas_cli.models (torch) is imported inside the commands, so `midas --help` and other commands start fast;
# models/registry.py (the --model help) imports no torch.

app = typer.Typer(help="Train and evaluate gesture-recognition models.\n\n"
                       "Models train on aligned, labelled sessions.",
                  no_args_is_help=True)

MODALITIES_OPT = typer.Option("auto", "--modalities", help="Comma list of emht, handkp, mtm, psm, image; auto "
                               "(default): emht where every session has it (MiDAS), else mtm,psm (JIGSAWS-style).")
FEATURES_OPT = typer.Option("auto", "--features", help="Comma list of pos, ori, vel, angvel, grasper, clutch; "
                             "auto (default): pos,ori,vel for emht (the paper), pos,vel,angvel,grasper for robot arms.")
TRAINING_PANEL = "Training"  # the options of training_options (below), shared by gestures and ablation
SPLIT_OPT = typer.Option("gesture", "--split", rich_help_panel=TRAINING_PANEL, help="gesture (stratified 60/20/20 "
                         "instances), loto, louo or loso (leave one trial / user / super-trial out).")
VAL_OPT = typer.Option("none", "--val", rich_help_panel=TRAINING_PANEL, help="loto/louo/loso model selection: none "
                       "(fixed epochs, last-epoch model; default, as in the papers) or inner (a seeded ~15% of the "
                       "training trials validate).")
BASELINE_OPT = typer.Option(True, "--baseline/--no-baseline", rich_help_panel=TRAINING_PANEL, help="Cross-validation "
                            "and ablation: also train the per-frame logistic-regression baseline and add its row to "
                            "every table.")
EPOCHS_OPT = typer.Option(None, "--epochs", rich_help_panel=TRAINING_PANEL, min=0, help="Training epochs (default: "
                          "the model's recipe: " + ", ".join(f"{e.name} {e.recipe.epochs}" for e in ENTRIES if e.recipe.epochs) + "; "
                          "an ensemble's members each their own; given, every member's).")
CAUSAL_OPT = typer.Option(False, "--causal", rich_help_panel=TRAINING_PANEL, help="Causal sequence models (frame t "
                          "sees frames <= t only: causal convolutions, masked attention), trained as such: the models "
                          "`record --live-model` can run. Per-frame baselines are causal as they are.")
DELAY_OPT = typer.Option(0.0, "--delay", rich_help_panel=TRAINING_PANEL, min=0.0, help="With --causal: label each "
                         "frame this many seconds late, from the frames up to then (live, a gesture is shown that "
                         "much later and the model sees that much of what follows it). Default 0: frame t from "
                         "frames <= t.")
MIN_SEGMENT_OPT = typer.Option("auto", "--min-segment", rich_help_panel=TRAINING_PANEL, help="The shortest "
                                "predicted segment (offline clean-up; shorter ones are decoded away, see --grammar, "
                                "or with --grammar none merged into their longer neighbour): seconds, none, or auto "
                                "(default): the 2nd percentile of the training split's gesture lengths. --causal: "
                                "decoded as live (see --decode-lag). The metrics without the clean-up are kept as raw.")
GRAMMAR_OPT = typer.Option("auto", "--grammar", rich_help_panel=TRAINING_PANEL, help="The clean-up as a decoding: "
                           "the labelling most likely from the frames' probabilities and the order of gestures in the "
                           "training labels (a change from a to b scores W x log P(b after a)), with segments all "
                           "--min-segment long. W: a number, none (the merge alone) or auto (default): 1 per Hz of "
                           "the model rate, 10 at 10 Hz.")
DECODE_LAG_OPT = typer.Option(0.0, "--decode-lag", rich_help_panel=TRAINING_PANEL, min=0.0, help="With --causal: "
                              "the clean-up decides each frame this many seconds after it, from the best labelling "
                              "so far, as `record --live-model` does (its decoded class); 0 (default): at once.")
CURVE_EVERY_OPT = typer.Option(0, "--curve-every", rich_help_panel=TRAINING_PANEL, min=0, help="Score the test split "
                               "every N epochs (and after the last) into run.json's history: a learning curve for "
                               "choosing --epochs on development data (never used to train or to pick weights).")
AUGMENT_SHIFT_OPT = typer.Option(None, "--augment-shift", rich_help_panel=TRAINING_PANEL, min=0.0, help="Training "
                                 "augmentation: each training sequence, each epoch, moves every --augment-features "
                                 "column by a constant drawn from N(0, (SD x its sd over the training split)^2): users' "
                                 "offsets blurred; 0: off. Nothing changes at test time. Default: the model's recipe.")
AUGMENT_FEATURES_OPT = typer.Option(None, "--augment-features", rich_help_panel=TRAINING_PANEL, help="The columns "
                                    "--augment-shift moves: pos, ori (orientations) or pos,ori. Default: the model's "
                                    "recipe.")
WEIGHTS_OPT = typer.Option(None, "--weights", rich_help_panel=TRAINING_PANEL, help="The weights a run keeps: last "
                           "(the last epoch's), average (the mean of the weights after each epoch of the second half) "
                           "or best-val (the best validation epoch's; without --val inner, the last). Default: the "
                           "model's recipe: " + ", ".join(f"{e.name} {e.recipe.selection}" for e in ENTRIES
                                                           if e.recipe.selection) + "; an ensemble's applies to every member.")
SEED_OPT = typer.Option(0, "--seed", rich_help_panel=TRAINING_PANEL, help="Seed of the split, the weights, batch "
                        "order and dropout.")
FOLD_BATCH_MODES = ("auto", "on", "off")  # models/fold_batch.py MODES (that module imports torch)
FOLD_BATCH_OPT = typer.Option("auto", "--fold-batch", help="--fold all, --executor local: train the folds together "
                              "in this one process, one stacked model per step (on), each alone (off); auto "
                              "(default): on with --accelerator cuda.")
MODEL_RATE_OPT = typer.Option(None, "--model-rate", callback=positive, help="Rate (Hz) the models see the aligned "
                              "table at (default: Raven-II 10; robot-arm kinematics alone, mtm/psm, 10; otherwise 30).")
EXCLUDE_OPT = typer.Option(False, "--exclude-clutch", help="Drop frames with the clutch pressed (train and test).")
SIDES_OPT = typer.Option("both", "--sides", help="Arms / hands to use: left, right or both (left,right).")
ROTATION_OPT = typer.Option("matrix", "--rotation", help="Robot orientation as a rotation matrix (9 per arm) or "
                            "quat (the logged quaternion, 4).")
NORMALISE_OPT = typer.Option("train", "--normalise", help="z-score fitted on the training split (train), per "
                             "trial (trial), or none.")


@dataclass(frozen=True)
class Training:
    """How models are trained and tested, as `train gestures` and `train ablation` both take it."""

    split: str
    val: str
    baseline: bool
    epochs: Optional[int]
    seed: int
    causal: bool
    min_segment: str
    grammar: str = "auto"
    curve_every: int = 0
    delay: float = 0.0
    decode_lag: float = 0.0
    augment_shift: Optional[float] = None
    augment_features: Optional[str] = None
    weights: Optional[str] = None

    def config(self, **fields: Any) -> TrainConfig:
        """A TrainConfig with these choices and ``fields`` (model, fold, device, ...)."""
        from midas_cli.models.train import TrainConfig

        return TrainConfig(split=self.split, validation=self.val, epochs=self.epochs, seed=self.seed,
                           causal=self.causal, min_segment=self.min_segment, grammar=self.grammar,
                           curve_every=self.curve_every,
                           delay_s=self.delay, decode_lag_s=self.decode_lag, augment_shift=self.augment_shift,
                           augment_features=self.augment_features, selection=self.weights, **fields)


# The "Training" panel of both commands' help, declared once.
training_options = option_group("training", Training, keyword_options(
    ("split", SPLIT_OPT, str), ("val", VAL_OPT, str), ("baseline", BASELINE_OPT, bool),
    ("epochs", EPOCHS_OPT, Optional[int]), ("seed", SEED_OPT, int), ("causal", CAUSAL_OPT, bool),
    ("min_segment", MIN_SEGMENT_OPT, str), ("grammar", GRAMMAR_OPT, str),
    ("curve_every", CURVE_EVERY_OPT, int), ("delay", DELAY_OPT, float),
    ("decode_lag", DECODE_LAG_OPT, float),
    ("augment_shift", AUGMENT_SHIFT_OPT, Optional[float]), ("augment_features", AUGMENT_FEATURES_OPT, Optional[str]),
    ("weights", WEIGHTS_OPT, Optional[str])))


def training_command(command: Callable[..., None]) -> Callable[..., None]:
    """gestures and ablation: batch commands (``batch``) that run torch (``device``) with the training
    options (``training``)."""
    return ex.batch_command(accelerator_option(training_options(command)))


def data_config(modalities: str, features: str, exclude_clutch: bool, model_rate: Optional[float], sides: str,
                rotation: str, normalise: str):
    from midas_cli.models.data import SIDES, DatasetConfig

    side_list = SIDES if sides.strip() == "both" else _split_list(sides)
    return DatasetConfig(_split_list(modalities), _split_list(features), exclude_clutch, model_rate,
                         sides=side_list, rotation=rotation, normalise=normalise)


def _parse_fold(text: str) -> int | None:
    """``--fold``: a fold index, or ``all`` (None)."""
    if text.strip().lower() == "all":
        return None
    try:
        fold = int(text)
    except ValueError:
        raise ConfigError(f"--fold must be a fold index (0, 1, ...) or 'all', got {text!r}") from None
    if fold < 0:
        raise ConfigError(f"--fold must be >= 0 or 'all', got {fold}")
    return fold


def session_paths(paths: list[Path]) -> list[Path]:
    found = [s for p in paths for s in find_sessions(p)]
    if not found:
        raise ConfigError(f"no session folders (with manifest.json) under {', '.join(map(str, paths))}")
    return found


def _split_list(text: str) -> tuple[str, ...]:
    return tuple(s.strip() for s in text.split(",") if s.strip())


def _epoch_progress(progress, label: str):
    task = progress.add_task(label, total=None, info="")

    def update(epoch: int, epochs: int, info: dict) -> None:
        val = info.get("val_accuracy")
        text = f"loss {info['loss']:.3f}" + (f"  val acc {val:.3f}" if val is not None else "")
        progress.update(task, completed=epoch, total=epochs, info=text)

    return update


def _progress():
    return progress_display(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                            TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TimeRemainingColumn())


def _render_metrics(metrics: dict, run_dir: Path) -> None:
    summary = metrics["test"]["summary"]
    table = Table("metric", "test", header_style="bold")
    for key in ("accuracy", "accuracy_with_background", "f1", "precision", "recall", "edit", "f1@10", "f1@25",
                "f1@50", "frames", "frames_all"):
        value = summary[key]
        table.add_row(key, f"{value:.3f}" if isinstance(value, float) else str(value))
    out.print(table)
    out.print("accuracy: labelled frames only; accuracy_with_background: all frames, unlabelled = 'background' "
              "(MS-TCN eval.py); definitions in metrics.json", markup=False)
    out.print(f"run folder: {run_dir}", markup=False)


@app.command()
@training_command
def gestures(
    sessions: list[Path] = SESSION_TREES_ARG,
    model: str = typer.Option("ensemble", "--model", help=model_help()),
    modalities: str = MODALITIES_OPT,
    features: str = FEATURES_OPT,
    fold: str = typer.Option("0", "--fold", help="loto/louo/loso: which trial/subject/super-trial (sorted) is held "
                             "out, or 'all': every fold into OUT/fold-<k>/ plus cv.json and cv.md."),
    fold_batch: str = FOLD_BATCH_OPT,
    model_rate: Optional[float] = MODEL_RATE_OPT,
    rate: Optional[float] = renamed_option("--rate", "--model-rate"),
    exclude_clutch: bool = EXCLUDE_OPT,
    sides: str = SIDES_OPT,
    rotation: str = ROTATION_OPT,
    normalise: str = NORMALISE_OPT,
    shuffle_labels: bool = typer.Option(False, "--shuffle-labels", help="Control run: permute training gesture classes."),
    out_dir: Path = typer.Option(..., "--out", help="New run folder (config, split, metrics, checkpoint, plots)."),
    eval_only: Optional[Path] = typer.Option(None, "--eval-only", help="Evaluate this checkpoint.pt on its test split."),
    as_json: bool = JSON_OPTION,
    *,
    batch: BatchOptions,
    device: str,
    training: Training,
) -> None:
    """Train (or with --eval-only, evaluate) a frame-wise gesture recogniser.

    Metrics go to stdout. With --fold all, each fold is a unit of --executor local (--jobs N) or slurm
    (one array task per fold; --accelerator cuda asks each for a GPU); the run folder is OUT/jobs/ unless
    --run-dir says otherwise, and a re-run trains only the folds not done.

    Example: midas train gestures sessions/ --model mstcn --modalities emht --features pos,ori,vel --split gesture --epochs 50 --out runs/emht-mstcn

    Example (leave one user out, every fold a SLURM task with a GPU): midas train gestures data/jigsaws/ --split louo --fold all --accelerator cuda --executor slurm --slurm-time 02:00:00 --out runs/louo
    """
    from midas_cli.models import cv
    from midas_cli.models.splits import GROUP_SPLITS
    from midas_cli.models.train import evaluate_checkpoint, train_run

    model_rate = take_renamed(model_rate, rate, "--rate", "--model-rate", error_line)
    if training.causal and normalise == "trial":
        raise ConfigError("--causal cannot use --normalise trial (it scales each trial by its whole recording, "
                          "the future included): use --normalise train or none")
    fold_index = _parse_fold(fold)
    if fold_batch not in FOLD_BATCH_MODES:
        raise ConfigError(f"--fold-batch must be one of {', '.join(FOLD_BATCH_MODES)}, got {fold_batch!r}")
    if fold_index is None and training.split not in GROUP_SPLITS:
        raise ConfigError(f"--fold all needs a group split ({', '.join(GROUP_SPLITS)}), not --split {training.split}")
    choice = batch.choice(gpu=device == "cuda")  # a CUDA unit asks SLURM for a GPU
    if fold_index is not None and (batch.executor != "local" or batch.jobs != 1 or batch.run_dir is not None):
        raise ConfigError("--executor, --jobs and --run-dir run the folds of --fold all; one fold is one run")
    paths = session_paths(sessions)
    if eval_only is None and fold_index is None:
        _train_folds(paths, data_config(modalities, features, exclude_clutch, model_rate, sides, rotation, normalise),
                     training.config(model=model, fold=0, device=device, shuffle_labels=shuffle_labels),
                     out_dir, cv.BASELINE if training.baseline else None, choice, as_json, fold_batch)
        return
    with _progress() as progress:
        if eval_only is not None:
            result = evaluate_checkpoint(paths, eval_only, out_dir, device)
        else:
            data = data_config(modalities, features, exclude_clutch, model_rate, sides, rotation, normalise)
            config = training.config(model=model, fold=fold_index or 0, device=device, shuffle_labels=shuffle_labels)
            result = train_run(paths, data, config, out_dir, _epoch_progress(progress, f"{model} epochs"))
    cv_root = out_dir.parent.parent if out_dir.parent.name == cv.BASELINE else out_dir.parent
    if eval_only is None and training.split in GROUP_SPLITS and out_dir.name == f"fold-{fold_index}" and cv.complete(cv_root):
        cv.summarise(cv_root)  # the last fold of a cluster run: aggregate
        error_line(f"every fold under {cv_root} has finished: wrote cv.json and cv.md there")
    if as_json:
        print_json({"run": str(result.out_dir), "test": result.metrics["test"]["summary"]})
        return
    _render_metrics(result.metrics, result.out_dir)


def _train_folds(paths: list[Path], data, config, out_dir: Path, baseline: Optional[str], choice, as_json: bool,
                 fold_batch: str = "auto") -> None:
    """--fold all: every fold (and baseline fold) a unit of the chosen executor, then cv.json / cv.md.
    With fold batching (local executor) the folds not started yet train first, together in this process;
    their units then find them finished."""
    from midas_cli.models import cv
    from midas_cli.models.cv_units import TASK, plan_units

    units = plan_units(paths, data, config, out_dir, baseline)
    _batched_folds(paths, data, config, cv.cv_jobs(config, out_dir, baseline), len(units), choice, fold_batch)
    if choice.run_dir is None:
        choice.run_dir = out_dir / "jobs"
    outcome = ex.run_plan(TASK, units, choice, f"{config.model} folds",
                          lambda display: _epoch_progress(display, f"{config.model} epochs"))
    if outcome.submitted:  # --no-wait: the run folder is printed
        return
    outcome.raise_failed("folds")
    _render_cv(cv.summarise(out_dir), out_dir, as_json)


def _batched_folds(paths: list[Path], data, config, jobs: list, n_units: int, choice, mode: str) -> None:
    """``--fold-batch``: train the pending folds of each model batched here (one stderr line says so), or
    say why --jobs N on CUDA is N processes sharing the GPU."""
    from midas_cli.models import cv, fold_batch

    n_folds = n_units // len(jobs)
    if config.curve_every and mode == "on":
        raise ConfigError("--curve-every scores each fold as it trains: it needs --fold-batch off (or auto)")
    if not fold_batch.enabled(mode, config.device, n_folds) or choice.executor != "local" or config.curve_every:
        if mode == "on" and choice.executor != "local":
            raise ConfigError("--fold-batch on trains the folds in this process: it needs --executor local")
        if choice.jobs > 1 and config.device == "cuda":
            error_line(f"midas: --jobs {choice.jobs} --accelerator cuda: {choice.jobs} processes share each GPU "
                       "(time-sliced); --fold-batch auto trains the folds together in one process")
        return
    for job_config, run_dirs in cv.pending_folds(jobs, range(n_folds)):
        error_line(f"midas: {len(run_dirs)} {job_config.model} folds train batched in one process on "
                   f"{config.device} (--fold-batch {mode}" + (f"; --jobs {choice.jobs} is not used for them)"
                                                             if choice.jobs > 1 else ")"))
        with _progress() as progress:
            fold_batch.train_folds(paths, data, job_config, run_dirs,
                                   _epoch_progress(progress, f"{job_config.model} epochs ({len(run_dirs)} folds)"))


def _render_cv(report: dict, root: Path, as_json: bool) -> None:
    if as_json:
        print_json({"cv": str(root / "cv.json"), "protocol": report["protocol"], "validation": report["validation"],
                    "mean": report["mean"], "sd": report["sd"], "pooled": report["pooled"],
                    **({"baseline": {k: report["baseline"][k] for k in ("mean", "sd", "pooled")}}
                       if "baseline" in report else {})})
        return
    out.print((root / "cv.md").read_text(encoding="utf-8"), markup=False)
    out.print(f"cross-validation folder: {root} (cv.json, cv.md, fold-<k>/)", markup=False)


@app.command("cv-summary")
def cv_summary(
    root: Path = typer.Argument(..., help="Cross-validation folder holding fold-<k>/ runs (and baseline/fold-<k>/)."),
    as_json: bool = JSON_OPTION,
) -> None:
    """Aggregate finished fold runs into cv.json and cv.md (missing folds are listed).

    Example: midas train cv-summary runs/louo-mstcn
    """
    from midas_cli.models import cv

    _render_cv(cv.summarise(root), root, as_json)


@app.command()
@training_command
def ablation(
    sessions: list[Path] = SESSION_TREES_ARG,
    models: str = typer.Option("transformer,mstcn", "--models", help="Comma list of models (table order)."),
    grid: Optional[str] = typer.Option(None, "--grid", help="';'-separated rows MODALITIES:FEATURES[:exclude-clutch] "
                                       "(default: the paper's Raven-II grid)."),
    fold: str = typer.Option("0", "--fold", help="loto/louo/loso: the held-out fold, or 'all': every cell is a "
                             "cross-validation (mean ± sd over folds)."),
    out_dir: Path = typer.Option(..., "--out", help="Folder for runs/ and table.md, table.tex, table.csv."),
    as_json: bool = JSON_OPTION,
    *,
    batch: BatchOptions,
    device: str,
    training: Training,
) -> None:
    """Train every model x grid row and write the paper-style table.

    The table's columns: Acc, F1, Prec., Rec. Each (model, row) cell is a unit of --executor local
    (--jobs N) or slurm (one array task per cell); the run folder is OUT/jobs/ unless --run-dir says
    otherwise, and a re-run trains only the cells not done.

    Example: midas train ablation sessions/ --models transformer,mstcn --grid "emht:pos,ori,vel:exclude-clutch;mtm:pos,ori,vel,grasper:exclude-clutch" --epochs 50 --out results/gestures
    """
    from midas_cli.models.ablation import check_ablation, finish_ablation, parse_grid
    from midas_cli.models.ablation_units import TASK, plan_units
    from midas_cli.session.outputs import out_folder

    choice = batch.choice(gpu=device == "cuda")  # a CUDA unit asks SLURM for a GPU
    paths = session_paths(sessions)
    rows = parse_grid(grid)
    fold_index = _parse_fold(fold)
    base = training.config(fold=fold_index or 0, device=device)
    model_list = check_ablation(list(_split_list(models)), base, fold_index is None, training.baseline)
    out_folder(out_dir)
    if choice.run_dir is None:
        choice.run_dir = out_dir / "jobs"
    units = plan_units(paths, rows, model_list, base, out_dir, cv=fold_index is None)
    outcome = ex.run_plan(TASK, units, choice, "ablation runs", lambda display: _epoch_progress(display, "epochs"))
    if outcome.submitted:  # --no-wait: the run folder is printed
        return
    outcome.raise_failed("ablation cells")
    report = finish_ablation(out_dir, outcome.results, base, fold_index is None)
    if as_json:
        print_json(report)
        return
    out.print((out_dir / "table.md").read_text(encoding="utf-8"), markup=False)
