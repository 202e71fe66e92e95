"""Cross-validation over the folds of a group split (loto, louo, loso), reported as papers report it.

``OUT/``
  ``fold-<k>/``            one ordinary run folder per fold (models/train.py): fold k holds out group k
                           (``run.json`` split ``group``); a fold is a unit of work that runs alone
                           (``midas train gestures --split louo --fold k --out OUT/fold-k``)
  ``baseline/fold-<k>/``   the per-frame baseline (models/baseline.py) on the same folds and features
  ``cv.json``              per-fold figures, mean and sd over folds, pooled figures, the protocol and the
                           validation choice; the baseline's figures under ``baseline``
  ``cv.md``                one row per fold, mean ± sd, pooled; the baseline's mean ± sd and pooled rows

*mean ± sd* is over folds (sample standard deviation, ddof = 1; none with one fold). *pooled* (micro) is
every test frame / segment of every fold evaluated together with models/metrics.py: accuracy over all
labelled test frames, edit averaged over all test sequences, F1@k from TP/FP/FN summed over all of
them (the MS-TCN way). *per video* (macro) scores each test video alone and averages over the videos
(accuracy, edit, F1@k): some papers report F1@k that way, and the two differ. Pooled figures are read
back from each fold's ``predictions/<trial>.csv`` (every test trial is one whole sequence in a group
split). Finished folds (``metrics.json`` present) are reused, so an
interrupted run resumes and folds run elsewhere are picked up by ``summarise`` (``midas train
cv-summary OUT``).
"""

from __future__ import annotations

import csv
import json
import logging
import re
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from midas_cli.errors import ConfigError, SessionError
from midas_cli.models import metrics as M
from midas_cli.models.data import DatasetConfig, build_dataset
from midas_cli.models.registry import LEGACY_TRAIN_CONFIG, MODELS
from midas_cli.models.splits import GROUP_SPLITS, fold_groups
from midas_cli.session.outputs import out_folder, out_target, write_text

if TYPE_CHECKING:  # torch is imported only to train: `midas train cv-summary` reads JSON and CSV
    from midas_cli.models.train import TrainConfig

log = logging.getLogger(__name__)

KEYS = ("accuracy", "edit", "f1@10", "f1@25", "f1@50", "f1", "precision", "recall")
TABLE_KEYS = ("accuracy", "edit", "f1@10", "f1@25", "f1@50")
TITLES = {"accuracy": "Acc", "edit": "Edit", "f1@10": "F1@10", "f1@25": "F1@25", "f1@50": "F1@50"}
PROTOCOLS = {"louo": "leave one user out: fold k tests on every trial of subject k (JIGSAWS: users B..I)",
             "loso": "leave one super-trial out: fold k tests on trial number k of every user (JIGSAWS: 1..5)",
             "loto": "leave one trial out: fold k tests on session k (sorted by name)"}
BASELINE = "baseline"
FOLD_DIR = re.compile(r"^fold-(\d+)$")

RunFn = Callable[[str, int, int], None]


def fold_dir(root: Path, fold: int) -> Path:
    return Path(root) / f"fold-{fold}"


def run_cv(sessions: Sequence[Path], data_config: DatasetConfig, config: TrainConfig, out_dir: Path,
           folds: Sequence[int] | None = None, baseline: str | None = BASELINE, on_fold: RunFn | None = None,
           progress: Callable[[int, int, dict], None] | None = None, batched: bool = False) -> dict | None:
    """Train the folds (all when ``folds`` is None) into ``out_dir/fold-<k>/`` and, unless ``baseline``
    is None or the model itself, the baseline into ``out_dir/baseline/fold-<k>/``; then write
    ``cv.json`` / ``cv.md`` when every fold is there. Returns the report (None while folds are missing).
    ``batched``: the folds not started yet train together in this process (models/fold_batch.py)."""
    if config.split not in GROUP_SPLITS:
        raise ConfigError(f"cross-validation needs a group split ({', '.join(GROUP_SPLITS)}), got {config.split!r}")
    groups = fold_groups(build_dataset(sessions, data_config), config.split)
    if len(groups) < 2:
        raise ConfigError(f"split {config.split} needs at least 2 groups, the data have {len(groups)}")
    wanted = list(range(len(groups))) if folds is None else list(folds)
    bad = [k for k in wanted if not 0 <= k < len(groups)]
    if bad:
        raise ConfigError(f"--fold {bad[0]} is out of range for {config.split}: 0..{len(groups) - 1}")
    out_dir = out_folder(out_dir)
    jobs = cv_jobs(config, out_dir, baseline)
    if batched:
        from midas_cli.models.fold_batch import train_folds

        for job_config, run_dirs in pending_folds(jobs, wanted):
            train_folds(sessions, data_config, job_config, run_dirs, progress)
    total = len(jobs) * len(wanted)
    done = 0
    for job_config, root in jobs:
        for k in wanted:
            done += 1
            if on_fold:
                on_fold(f"{job_config.model} fold {k} ({config.split} {groups[k]})", done, total)
            run_fold(sessions, data_config, replace(job_config, fold=k), fold_dir(root, k), progress)
    return summarise(out_dir) if complete(out_dir) else None


def cv_jobs(config: TrainConfig, out_dir: Path, baseline: str | None = BASELINE) -> list[tuple[TrainConfig, Path]]:
    """The model's folds under ``out_dir`` and, unless ``baseline`` is None or the model itself, the
    baseline's (its own recipe, no model options) under ``out_dir/baseline``."""
    jobs = [(config, Path(out_dir))]
    if baseline and baseline != config.model:
        jobs.append((replace(config, model=baseline, model_options={}, lr=None), Path(out_dir) / BASELINE))
    return jobs


def pending_folds(jobs: Sequence[tuple[TrainConfig, Path]], folds: Sequence[int]) -> list[tuple[TrainConfig, dict[int, Path]]]:
    """Per job of :func:`cv_jobs`, its ``folds`` not started yet (no ``run.json``), where more than one
    is left: what ``fold_batch.train_folds`` trains together. A started fold is left to ``run_fold``."""
    found = []
    for config, root in jobs:
        run_dirs = {k: fold_dir(root, k) for k in folds if not (fold_dir(root, k) / "run.json").exists()}
        if len(run_dirs) > 1:
            found.append((config, run_dirs))
    return found


def run_fold(sessions: Sequence[Path], data_config: DatasetConfig, config: TrainConfig, run_dir: Path,
             progress: Callable[[int, int, dict], None] | None = None) -> None:
    """One fold as an ordinary run; a finished one (metrics.json) is kept."""
    from midas_cli.models.train import train_run

    if (run_dir / "metrics.json").is_file():
        log.info("%s: finished fold reused", run_dir)
        return
    train_run(sessions, data_config, config, run_dir, progress)


def _fold_runs(root: Path) -> dict[int, Path]:
    found = {}
    for child in sorted(Path(root).iterdir()) if Path(root).is_dir() else []:
        match = FOLD_DIR.match(child.name)
        if match and (child / "metrics.json").is_file() and (child / "run.json").is_file():
            found[int(match[1])] = child
    return found


def _expected(runs: dict[int, Path]) -> list[str]:
    first = json.loads((next(iter(runs.values())) / "run.json").read_text(encoding="utf-8"))
    return list(first["split"].get("groups") or [])


def complete(root: Path) -> bool:
    """Every fold of ``root`` (and of ``root/baseline`` when present) has finished."""
    for folder in (Path(root), Path(root) / BASELINE):
        runs = _fold_runs(folder)
        if folder == Path(root) and not runs:
            return False
        if runs and (not _expected(runs) or len(runs) < len(_expected(runs))):
            return False  # a run without its split's groups (an older midas) cannot say how many folds exist
    return True


def collect(root: Path) -> dict:
    """Per-fold, mean, sd and pooled figures of the fold runs under ``root`` (no files written)."""
    runs = _fold_runs(root)
    if not runs:
        raise SessionError(f"{root} holds no finished fold (fold-<k>/ with run.json and metrics.json)")
    records = {k: json.loads((p / "run.json").read_text(encoding="utf-8")) for k, p in runs.items()}
    first = records[min(records)]
    same = ("dataset_config", "data_fingerprint", "classes", "model")
    # the fold differs by design; the device (cpu/cuda) a cluster job ran on does not change what is trained
    train_keys = lambda r: {k: v for k, v in {**LEGACY_TRAIN_CONFIG, **r["train_config"]}.items()  # noqa: E731
                            if k not in ("fold", "device")}
    for k, record in records.items():
        differs = [key for key in same if record.get(key) != first.get(key)]
        differs += ["train_config"] if train_keys(record) != train_keys(first) else []
        if differs:
            raise ConfigError(f"{runs[k]} was trained differently from {runs[min(records)]} ({', '.join(differs)}): "
                              "one cross-validation needs the same data and configuration in every fold")
    split = first["split"]
    if split["kind"] not in GROUP_SPLITS:
        raise ConfigError(f"{runs[min(runs)]}: split {split['kind']!r} is not a group split ({', '.join(GROUP_SPLITS)})")
    groups = list(split.get("groups") or [])
    classes = first["classes"]
    folds, preds, truths = [], [], []
    for k in sorted(runs):
        summary = json.loads((runs[k] / "metrics.json").read_text(encoding="utf-8"))["test"]["summary"]
        fold_split = records[k]["split"]
        test = [u[0] for u in fold_split["test"]]
        folds.append({"fold": k, "group": fold_split.get("group"), "run": runs[k].name,
                      "test_trials": test, "train_trials": [u[0] for u in fold_split["train"]],
                      "val_trials": [u[0] for u in fold_split["val"]], "frames": summary["frames"],
                      **{key: summary[key] for key in KEYS}})
        for name in test:
            p, y = _read_predictions(runs[k] / "predictions" / f"{name}.csv", classes)
            preds.append(p)
            truths.append(y)
    values = {key: np.array([f[key] for f in folds], dtype=float) for key in KEYS}
    pooled = M.evaluate(preds, truths, classes)["summary"]
    per_video = per_video_means(preds, truths)
    return {"protocol": split["kind"], "protocol_text": PROTOCOLS[split["kind"]],
            "validation": split.get("validation") or "next group (before issue 19)",
            "model": first["model"], "epochs": _epochs(first), "seed": split["seed"], "clean_up": _clean_up(first),
            "dataset_config": first["dataset_config"], "data_fingerprint": first["data_fingerprint"],
            "groups": groups, "n_folds": len(groups) or len(folds),
            "missing_folds": [k for k in range(len(groups)) if k not in runs],
            "folds": folds,
            "mean": {key: float(v.mean()) for key, v in values.items()},
            "sd": {key: (float(v.std(ddof=1)) if len(v) > 1 else None) for key, v in values.items()},
            "pooled": {**{key: pooled[key] for key in KEYS}, "frames": pooled["frames"], "sequences": len(preds)},
            "per_video": per_video,
            "definitions": {"mean/sd": "over folds; sd = sample standard deviation (ddof 1), null with one fold",
                            "pooled": "all test frames / sequences of all folds evaluated together (micro): "
                                      "F1@k from TP/FP/FN summed over every test video (the MS-TCN way)",
                            "per_video": "each test video scored alone, then the mean over videos (macro): "
                                         "accuracy, edit and F1@k as papers that average per video report them",
                            "units": "accuracy, f1, precision, recall: fractions; edit, f1@k: 0-100",
                            **M.DEFINITIONS}}


def _clean_up(run: dict) -> str:
    """What the scored predictions went through after the network (``--min-segment``, ``--grammar``)."""
    minimum, weight = run.get("min_segment_frames", 0), run.get("grammar_weight", 0.0)
    if not minimum and not weight:
        return "none (the network's own predictions)"
    how = f"decoded with the training split's gesture order, weight {weight:g}" if weight else "short segments merged"
    lag = run.get("decode_lag_frames")
    if lag is not None:  # a causal run: decoded frame by frame, as live
        how = (f"decoded frame by frame as live, each frame {lag} frame(s) after it, "
               + (f"with the training split's gesture order, weight {weight:g}" if weight else "no gesture order"))
    return f"{how}, segments at least --min-segment {run['train_config']['min_segment']} long (raw figures: each " \
           "fold's metrics.json)"


def _epochs(run: dict) -> int | str | None:
    """The epochs a fold trained: its own, or an ensemble's members' joined by + (e.g. "20+10+20")."""
    members = run.get("recipe", {}).get("members")
    if run["train_config"]["epochs"] is None and members:
        return "+".join(str(m["epochs"]) for m in members)
    return run["train_config"]["epochs"]


def per_video_means(preds: Sequence[np.ndarray], truths: Sequence[np.ndarray]) -> dict[str, float | int]:
    """Accuracy, edit and F1@k of each test video alone, averaged over the videos (0-1 for accuracy,
    0-100 for the rest, as ``metrics.evaluate``)."""
    accuracy, edit, f1 = [], [], {k: [] for k in M.OVERLAPS}
    for p, y in zip(preds, truths):
        labelled = y != M.IGNORE
        accuracy.append(float((p[labelled] == y[labelled]).mean()) if labelled.any() else np.nan)
        edit.append(M.edit_score(p, y, M.IGNORE))
        for overlap in M.OVERLAPS:
            f1[overlap].append(M.f1_from_counts(*(int(c) for c in M.overlap_counts(p, y, overlap, M.IGNORE))))
    return {"accuracy": float(np.nanmean(accuracy)), "edit": float(np.mean(edit)),
            **{f"f1@{int(k * 100)}": float(np.mean(v)) for k, v in f1.items()}, "videos": len(preds)}


def summarise(root: Path) -> dict:
    """Aggregate the finished folds under ``root`` (and ``root/baseline``) into cv.json and cv.md."""
    root = Path(root)
    report = collect(root)
    if _fold_runs(root / BASELINE):
        report["baseline"] = collect(root / BASELINE)
    for part in (report, report.get("baseline")):
        if part and part["missing_folds"]:
            log.warning("%s: folds %s not finished; the figures cover %d of %d folds", root,
                        ", ".join(map(str, part["missing_folds"])), len(part["folds"]), part["n_folds"])
    write_text(out_target(root / "cv.json"), json.dumps(report, indent=2) + "\n")
    write_text(out_target(root / "cv.md"), markdown(report))
    return report


def _read_predictions(path: Path, classes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    index = {name: i for i, name in enumerate(classes)}
    if not path.is_file():
        raise SessionError(f"{path} is missing: the fold's predictions are needed for the pooled figures")
    with path.open(encoding="utf-8", newline="") as handle:
        rows = list(csv.DictReader(handle))
    try:
        truth = [index[r["truth"]] if r["truth"] else M.IGNORE for r in rows]
        pred = [index[r["prediction"]] if r["prediction"] else M.IGNORE for r in rows]
    except KeyError as exc:
        raise SessionError(f"{path}: label {exc} is not among the run's classes") from exc
    return np.asarray(pred, dtype=np.int64), np.asarray(truth, dtype=np.int64)


def cell(report: dict, key: str, which: str = "mean") -> str:
    """A figure as papers print it: percent for accuracy, 0-100 for edit/F1@k; mean ± sd."""
    scale = 100.0 if key in ("accuracy", "f1", "precision", "recall") else 1.0
    if which in ("pooled", "per_video"):
        value = report.get(which, {}).get(key)
        return "" if value is None else f"{value * scale:.1f}"
    sd = report["sd"][key]
    return f"{report['mean'][key] * scale:.1f}" + (f" ± {sd * scale:.1f}" if sd is not None else "")


def model_title(name: str) -> str:
    """The registry's title of model ``name`` (a name it does not know, from an old report: as it is)."""
    return MODELS[name].title if name in MODELS else name


def markdown(report: dict) -> str:
    name = model_title(report["model"])
    lines = [f"# {report['protocol'].upper()} cross-validation: {name}", "",
             f"Protocol: {report['protocol_text']}; {len(report['folds'])} of {report['n_folds']} folds.  ",
             f"Validation: {report['validation']}; {report['epochs']} epochs; seed {report['seed']}.  ",
             f"Clean-up: {report.get('clean_up', 'not recorded')}.  ",
             "Acc in %, edit and F1@k 0-100; mean ± sd over folds (sample sd); pooled = all test frames and "
             "segments of all folds together (F1@k from TP/FP/FN summed over every test video, the MS-TCN way); "
             "per video = each test video scored alone, then averaged.", "",
             "| Model | Fold | Test group | " + " | ".join(TITLES[k] for k in TABLE_KEYS) + " |",
             "|---|---|---|" + "---:|" * len(TABLE_KEYS)]
    for fold in report["folds"]:
        scaled = [f"{fold[k] * (100.0 if k == 'accuracy' else 1.0):.1f}" for k in TABLE_KEYS]
        lines.append(f"| {name} | {fold['fold']} | {fold['group']} | " + " | ".join(scaled) + " |")
    for part, title in ((report, name), (report.get("baseline"), None)):
        if not part:
            continue
        title = title or model_title(part["model"])
        lines.append(f"| {title} | mean ± sd | | " + " | ".join(cell(part, k) for k in TABLE_KEYS) + " |")
        lines.append(f"| {title} | pooled | | " + " | ".join(cell(part, k, "pooled") for k in TABLE_KEYS) + " |")
        lines.append(f"| {title} | per video | | " + " | ".join(cell(part, k, "per_video") for k in TABLE_KEYS) + " |")
    if report["missing_folds"]:
        lines += ["", f"Missing folds (not finished): {', '.join(map(str, report['missing_folds']))}"]
    return "\n".join(lines) + "\n"
