"""Gesture recognition on real kinematics: leave-one-user-out over every fold of the JIGSAWS development
tasks (Knot Tying, Needle Passing), every model at its defaults, through the CLI.

Data: the jigsaws-dev folder (default ``../shared/data/jigsaws-dev`` beside the repository; its archives
are never copied into the repository). Each task's archive is extracted into the work folder
(``--work``, default ``$TMPDIR/midas-jigsaws-dev``), imported (``midas import jigsaws``) and aligned
(``midas align``); every step already done there is skipped. Then, per task and model,
``midas train gestures SESSIONS --model M --split louo --fold all`` (defaults otherwise; ``--epochs``
overrides the recipe) into ``WORK/runs/<task>/<model>``; the first neural model's run also trains the
per-frame baseline (the CLI's ``--baseline`` default), later runs pass ``--no-baseline``. A run whose
folds are all finished is not trained again: its recorded wall time is reused (``timing.json``), and a
run resumed after an interruption is marked ``resumed`` (its wall time covers only the folds it trained).

From each run's ``cv.json``: accuracy, edit and F1@{10,25,50} pooled over all test videos (the MS-TCN way)
and averaged per video, mean and sd of accuracy and edit over folds, and each fold's accuracy; with the
wall time, the load average and the machine (cores, CPU model, torch version, threads per worker).
``--causal`` trains the sequence models' causal variants instead (``train gestures --causal``, the models
``record --live-model`` runs) into ``<model>-causal``: their rows sit beside the offline ones, with the
accuracy difference. Results accumulate in ``results/gestures_jigsaws.json`` (rows keyed by task, model,
epochs and causal, so parts can be run one at a time) and ``results/gestures_jigsaws.md``; ``report.py`` puts the table into
BENCHMARKS.md. One progress line per finished (task, model) on stderr. ``--report-only`` trains nothing and
reads the run folders as they are (an unfinished run: its finished folds, marked so); ``--note`` keeps a
dated remark (e.g. the machine's load) under the tables.

Run it niced on a shared machine:

    nice -n 19 .venv/bin/python benchmarks/gestures_jigsaws.py --jobs 2
    nice -n 19 .venv/bin/python benchmarks/gestures_jigsaws.py --tasks knot_tying --models baseline,mstcn
    .venv/bin/python benchmarks/gestures_jigsaws.py --tasks knot_tying --models mstcn --epochs 1   # smoke
    nice -n 19 .venv/bin/python benchmarks/gestures_jigsaws.py --jobs 2 --causal --models mstcn,transformer
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import RESULTS, load_average, machine_info  # noqa: E402
from report_gestures import gestures_jigsaws_table  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
NAME = "gestures_jigsaws"
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "jigsaws-dev"
DEFAULT_WORK = Path(tempfile.gettempdir()) / "midas-jigsaws-dev"
NEURAL = ("mstcn", "transformer", "ensemble")
MODELS = ("baseline", *NEURAL)
METRICS = ("accuracy", "edit", "f1@10", "f1@25", "f1@50")
TARGET_EDIT = 85.0

# Every CLI spelling this script uses, in one place (commands/ options may be renamed: adjust them here).
CLI_IMPORT = ("import", "jigsaws")
CLI_ALIGN = ("align",)
CLI_TRAIN = ("train", "gestures", "--split", "louo", "--fold", "all")
OPT_OUT, OPT_JOBS, OPT_MODEL, OPT_EPOCHS = "--out", "--jobs", "--model", "--epochs"
OPT_NO_BASELINE, OPT_JSON, OPT_CAUSAL = "--no-baseline", "--json", "--causal"


@dataclass(frozen=True)
class Task:
    """A development task: its archive, the folder the archive unpacks to, and the figures to compare."""

    archive: str
    folder: str
    title: str
    literature_accuracy: float  # jigsaws-dev README: published LOUO, kinematics only
    target_accuracy: float  # issue 27's target at the defaults


TASKS = {"knot_tying": Task("knot_tying.tar.xz", "Knot_Tying", "Knot Tying", 0.79, 0.80),
         "needle_passing": Task("needle_passing.tar.xz", "Needle_Passing", "Needle Passing", 0.74, 0.76)}


def midas(*args: str, jobs: int | None = None) -> str:
    """Run ``python -m midas_cli ARGS`` (the repository's code first on the path); stdout, or raise
    RuntimeError with the command's last stderr lines."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    extra = [OPT_JOBS, str(jobs)] if jobs else []
    proc = subprocess.run([sys.executable, "-m", "midas_cli", *args, *extra], capture_output=True, text=True,
                          env=env, cwd=ROOT)
    if proc.returncode != 0:
        raise RuntimeError(f"midas {' '.join(args[:2])} failed ({proc.returncode}): {proc.stderr[-3000:]}")
    return proc.stdout


def extract(data: Path, task: Task, work: Path) -> Path:
    """The task's unpacked folder under ``work/extract`` (extracted now unless it is already there)."""
    target = work / "extract" / task.folder
    if (target / "kinematics").is_dir():
        return target
    archive = data / task.archive
    if not archive.is_file():
        raise SystemExit(f"{archive}: no such archive (give the jigsaws-dev folder as DATA)")
    staging = Path(tempfile.mkdtemp(prefix="extract-", dir=work))
    with tarfile.open(archive) as tar:
        tar.extractall(staging, filter="data")  # refuses absolute paths, links out of the folder, devices
    if not (staging / task.folder / "kinematics").is_dir():
        raise SystemExit(f"{archive} holds no {task.folder}/kinematics folder")
    target.parent.mkdir(parents=True, exist_ok=True)
    (staging / task.folder).rename(target)
    shutil.rmtree(staging)
    return target


def sessions_in(folder: Path) -> list[Path]:
    """Session folders (with a manifest) directly under ``folder``."""
    return sorted(p for p in folder.iterdir() if (p / "manifest.json").is_file()) if folder.is_dir() else []


def prepare(data: Path, name: str, work: Path, jobs: int) -> tuple[Path, dict[str, Any]]:
    """Extract, import and align one task (each step skipped where done); the sessions folder and times."""
    sessions_dir = work / "sessions" / name
    times: dict[str, Any] = {}
    if not sessions_dir.exists():  # imported beside it, then renamed: an interrupted import is redone
        source, staging = extract(data, TASKS[name], work), sessions_dir.with_name(f".{name}.importing")
        shutil.rmtree(staging, ignore_errors=True)
        staging.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.monotonic()
        midas(*CLI_IMPORT, str(source), OPT_OUT, str(staging), OPT_JSON)
        times["import_s"] = round(time.monotonic() - t0, 1)
        staging.rename(sessions_dir)
    todo = [s for s in sessions_in(sessions_dir) if not (s / "derived" / "aligned.npz").is_file()]
    if todo:
        t0 = time.monotonic()
        midas(*CLI_ALIGN, *map(str, todo), OPT_JSON, jobs=jobs)
        times["align_s"] = round(time.monotonic() - t0, 1)
    return sessions_dir, {"sessions": len(sessions_in(sessions_dir)), **times}


def run_dir(work: Path, name: str, model: str, epochs: int | None, causal: bool = False, variant: str = "") -> Path:
    """Where one (task, model) cross-validation lives; runs at other epochs than the recipe's, causal runs
    and runs of a named variant (other training options) apart."""
    stem = f"{model}-causal" if causal else model
    folder = stem if epochs is None else f"{stem}-e{epochs}"
    return work / "runs" / name / (f"{folder}--{variant}" if variant else folder)


def finished_folds(root: Path) -> int:
    """Folds with their metrics written under ``root`` (the CLI reuses them on a re-run)."""
    return sum(1 for f in root.glob("fold-*/metrics.json")) if root.is_dir() else 0


def train(sessions: Path, model: str, out: Path, epochs: int | None, jobs: int, baseline: bool,
          causal: bool = False, extra: tuple[str, ...] = ()) -> dict[str, Any]:
    """One LOUO cross-validation through the CLI, or the timing recorded when it last completed."""
    done = recorded_timing(out)
    if done and (not baseline or (out / "baseline").is_dir()):
        return {**done, "reused": True}
    args = [*CLI_TRAIN, str(sessions), OPT_MODEL, model, OPT_OUT, str(out)]
    args += [OPT_EPOCHS, str(epochs)] if epochs is not None else []
    args += [] if baseline and model != "baseline" else [OPT_NO_BASELINE]
    args += [OPT_CAUSAL] if causal else []
    args += list(extra)
    before, load_before, t0 = finished_folds(out), load_average(), time.monotonic()
    midas(*args, jobs=jobs)
    timing = {"wall_s": round(time.monotonic() - t0, 1), "jobs": jobs, "resumed": before > 0,
              "folds_done_before": before, "load_average_before_after": [load_before, load_average()],
              "command": "midas " + " ".join(args + [OPT_JOBS, str(jobs)]),
              "finished_utc": utc_now()}
    (out / "timing.json").write_text(json.dumps(timing, indent=2) + "\n", encoding="utf-8")
    return timing


def fold_seconds(out: Path, model: str) -> dict[int, float]:
    """Each finished fold's own training time (the jobs folder's done markers: ``seconds``), by fold."""
    seconds = {}
    for marker in sorted(out.glob("jobs/units/*/done.json")):
        try:
            done = json.loads(marker.read_text(encoding="utf-8"))
            name, secs = str(done["name"]).split(), float(done["seconds"])
        except (OSError, ValueError, KeyError, TypeError):
            continue  # a marker being written, or not the CLI's: left out
        if len(name) >= 3 and name[0] == model and name[1] == "fold" and name[2].isdigit():
            seconds[int(name[2])] = round(secs, 1)
    return seconds


def cross_validation(out: Path, part: str | None = None) -> dict[str, Any] | None:
    """cv.json of a finished run (or its baseline part); for an unfinished one, the finished folds'
    figures from the library's own aggregation (``models.cv.collect``, which writes nothing); None
    without a finished fold."""
    if (out / "cv.json").is_file():
        cv = json.loads((out / "cv.json").read_text(encoding="utf-8"))
        return cv if part is None else cv.get(part)
    sys.path.insert(0, str(ROOT))
    from midas_cli.models import cv as cv_lib

    root = out if part is None else out / part
    return cv_lib.collect(root) if any(root.glob("fold-*/metrics.json")) else None


def submissions(out: Path) -> tuple[str | None, int | None]:
    """When the run's first submission went to the local executor, and the last one's --jobs."""
    try:
        subs = json.loads((out / "jobs" / "submissions.json").read_text(encoding="utf-8"))
        return str(subs[0]["submitted"]), int(subs[-1]["jobs"])
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        return None, None


def recorded_timing(out: Path) -> dict[str, Any] | None:
    """A finished run's timing: the one this script recorded, else (a run started by hand) its first
    submission to its cv.json; None while cv.json is missing."""
    if not (out / "cv.json").is_file():
        return None
    if (out / "timing.json").is_file():
        return dict(json.loads((out / "timing.json").read_text(encoding="utf-8")))
    started, jobs = submissions(out)
    if started is None:
        return None
    wall = (out / "cv.json").stat().st_mtime - datetime.fromisoformat(started).timestamp()
    return {"wall_s": round(wall, 1), "jobs": jobs, "started": started, "wall_from": "submission to cv.json"}


def unfinished_timing(out: Path) -> dict[str, Any]:
    """--report-only: the timing of a finished run, or what an unfinished one can say (its start)."""
    done = recorded_timing(out)
    if done:
        return done
    started, jobs = submissions(out)
    return {"wall_s": None, "unfinished": True, "started": started, "jobs": jobs, "reported_utc": utc_now()}


def utc_now() -> str:
    """Now, UTC, to the second."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def figures(cv: dict[str, Any]) -> dict[str, Any]:
    """The figures of one cross-validation report (cv.json, or its ``baseline`` part)."""
    return {"pooled": {k: cv["pooled"][k] for k in METRICS}, "per_video": {k: cv["per_video"][k] for k in METRICS},
            "fold_mean": {k: cv["mean"][k] for k in ("accuracy", "edit")},
            "fold_sd": {k: cv["sd"][k] for k in ("accuracy", "edit")},
            "folds": [{"fold": f["fold"], "user": f["group"], "accuracy": f["accuracy"], "edit": f["edit"],
                       "test_trials": len(f["test_trials"])} for f in cv["folds"]],
            "n_folds": cv["n_folds"], "missing_folds": cv["missing_folds"], "videos": cv["per_video"]["videos"],
            "frames": cv["pooled"]["frames"], "epochs": cv["epochs"], "model": cv["model"],
            "inputs": {k: cv["dataset_config"].get(k) for k in ("modalities", "features", "sides", "rate_hz")}}


def training_settings(out: Path) -> dict[str, Any] | None:
    """The run's training settings as ``train gestures`` resolved them (its first finished fold's
    ``train_config`` without the fold and device): what the run trained with, defaults included, so that a
    row is compared with runs that trained the same way even after a default changed (report_gestures
    ``offline_partner``). None where no fold has finished."""
    for run in sorted(out.glob("fold-*/run.json")):
        try:
            config = json.loads(run.read_text(encoding="utf-8"))["train_config"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if isinstance(config, dict):
            return {k: v for k, v in config.items() if k not in ("fold", "device")}
    return None


def learning_curve(out: Path) -> dict[str, Any] | None:
    """A run trained with ``--curve-every``: at each scored epoch that every finished fold has, the
    pooled accuracy (correct / labelled test frames over all folds) and the mean edit over test videos,
    raw predictions (no --min-segment); ``by_fold``: each fold's (held-out group's) [correct, frames] by
    epoch, so that two runs are compared on the folds both have. None for a run without it."""
    points: dict[int, list[dict[str, Any]]] = {}
    by_fold: dict[str, dict[str, list[int]]] = {}
    folds = 0
    for run in sorted(out.glob("fold-*/run.json")):
        try:
            saved = json.loads(run.read_text(encoding="utf-8"))
            history = saved["history"]
        except (OSError, ValueError, KeyError):
            continue
        scored = {int(e["epoch"]): e["test_curve"] for e in history if isinstance(e, dict) and "test_curve" in e}
        if not scored:
            continue
        folds += 1
        group = (saved.get("split") or {}).get("group") or run.parent.name
        by_fold[str(group)] = {str(e): [int(p["correct"]), int(p["frames"])] for e, p in sorted(scored.items())}
        for epoch, point in scored.items():
            points.setdefault(epoch, []).append(point)
    epochs = sorted(e for e, p in points.items() if len(p) == folds)
    if not folds or not epochs:
        return None
    return {"folds": folds, "epochs": epochs, "by_fold": by_fold,
            "accuracy": [sum(p["correct"] for p in points[e]) / max(1, sum(p["frames"] for p in points[e]))
                         for e in epochs],
            "edit": [float(np.mean([x for p in points[e] for x in p["edit"]])) for e in epochs]}


def run_task(data: Path, name: str, models: list[str], args: argparse.Namespace) -> list[dict[str, Any]]:
    """Every requested model of one task; the rows (the baseline read from the first neural run)."""
    sessions, prep = (args.work / "sessions" / name, {}) if args.report_only else prepare(data, name, args.work,
                                                                                          args.jobs)
    neural = [m for m in NEURAL if m in models]
    with_baseline = "baseline" in models and not args.causal  # the per-frame baseline is causal as it is
    rows = []
    for i, model in enumerate(neural or ["baseline"]):
        out = run_dir(args.work, name, model, args.epochs, args.causal, args.variant)
        if args.report_only:
            timing = {**unfinished_timing(out), "reused": True}
        else:
            try:
                timing = train(sessions, model, out, args.epochs, args.jobs, baseline=i == 0 and with_baseline,
                               causal=args.causal, extra=tuple(args.train_args.split()))
            except RuntimeError as exc:  # a failed fold: said, and the other models still run
                print(f"{name} {model}: FAILED, see {out}/jobs/logs: {exc}", file=sys.stderr, flush=True)
                continue
        wanted = [model] + (["baseline"] if with_baseline and model != "baseline" else [])
        for row_model in wanted:
            part = cross_validation(out, None if row_model == model else "baseline")
            if part is None:
                continue
            shared = "" if row_model == model else f" (trained inside the {model} run)"
            row = {"task": name, "model": row_model, "epochs_option": args.epochs, "causal": args.causal,
                   "run_dir": str(out), "variant": args.variant if row_model == model else "",
                   "train_args": args.train_args if row_model == model else "",
                   "timing": timing, "trained_in": model, "prepare": prep, **figures(part),
                   "fold_seconds": fold_seconds(out, row_model),
                   "curve": learning_curve(out) if row_model == model else None,
                   "training": training_settings(out) if row_model == model else None}
            rows.append(row)
            wall = "unfinished" if timing["wall_s"] is None else f"{timing['wall_s']:g} s"
            print(f"{name} {row_model}{' (causal)' if args.causal else ''}: {wall}{shared}{' (reused)' if timing.get('reused') else ''}"
                  f", {len(row['folds'])}/{row['n_folds']} folds, acc {row['pooled']['accuracy']:.3f}, "
                  f"edit {row['pooled']['edit']:.1f}", file=sys.stderr, flush=True)
    return rows


def torch_facts(jobs: int) -> dict[str, Any]:
    """torch version, the threads each training worker gets (the local executor's OMP_NUM_THREADS), the GPU if any."""
    import torch

    env = os.environ.get("OMP_NUM_THREADS")
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {"torch": torch.__version__, "jobs": jobs,
            "threads_per_worker": int(env) if env else max(1, (os.cpu_count() or 1) // jobs),
            "niceness": os.nice(0), **({"gpu": gpu} if gpu else {})}


def merge(old: list[dict[str, Any]], new: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Earlier rows kept unless this run measured the same (task, model, epochs, causal, variant) again."""
    key = lambda r: (r["task"], r["model"], r["epochs_option"], bool(r.get("causal")), r.get("variant", ""))  # noqa: E731
    fresh = {key(r) for r in new}
    return [r for r in old if key(r) not in fresh] + new


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", nargs="?", type=Path, default=DEFAULT_DATA, help="the jigsaws-dev folder")
    parser.add_argument("--work", type=Path, default=DEFAULT_WORK, help="extracted data, sessions and runs")
    parser.add_argument("--tasks", default=",".join(TASKS), help=f"comma list of {', '.join(TASKS)}")
    parser.add_argument("--models", default=",".join(MODELS), help=f"comma list of {', '.join(MODELS)}")
    parser.add_argument("--epochs", type=int, default=None, help="override every model's recipe epochs")
    parser.add_argument("--causal", action="store_true",
                        help="train the sequence models' causal variants (rows beside the offline ones; no baseline)")
    parser.add_argument("--jobs", type=int, default=2, help="folds trained at once (worker processes)")
    parser.add_argument("--variant", default="", help="name of a variant: rows and run folders of its own")
    parser.add_argument("--train-args", default="", help="extra options for train gestures (with --variant)")
    parser.add_argument("--note", help="a dated remark on this run for the report (e.g. the machine's load)")
    parser.add_argument("--report-only", action="store_true",
                        help="train nothing: rows from what the run folders hold now (unfinished runs: their folds)")
    args = parser.parse_args()
    tasks, models = args.tasks.split(","), args.models.split(",")
    unknown = sorted(set(tasks) - set(TASKS)) + sorted(set(models) - set(MODELS))
    if bool(args.variant) != bool(args.train_args):
        parser.error("--variant and --train-args go together")
    if unknown or args.jobs < 1 or (args.epochs is not None and args.epochs < 1):
        parser.error(f"unknown task/model {', '.join(unknown)}" if unknown else "--jobs and --epochs must be >= 1")
    args.work.mkdir(parents=True, exist_ok=True)
    facts = {"machine": machine_info(), **torch_facts(args.jobs)}
    note = [f"{facts['machine']['date_utc'][:10]}: {args.note}"] if args.note else []
    report: dict[str, Any] = {}
    for name in tasks:  # saved after each task: an interrupted run keeps what finished
        report = save([{**row, **facts} for row in run_task(args.data, name, models, args)], facts, args.data, note)
        note = []
    print("\n".join(gestures_jigsaws_table(report)))


def save(rows: list[dict[str, Any]], facts: dict[str, Any], data: Path, note: list[str]) -> dict[str, Any]:
    """Merge ``rows`` (and ``note``) into results/gestures_jigsaws.json (and its .md table); the report."""
    path = RESULTS / f"{NAME}.json"
    old = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}
    report = {**facts, "data": str(data), "tasks": {k: vars(v) for k, v in TASKS.items()},
              "target_edit": TARGET_EDIT, "rows": merge(old.get("rows", []), rows),
              "notes": old.get("notes", []) + note}
    RESULTS.mkdir(exist_ok=True)
    path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    (RESULTS / f"{NAME}.md").write_text("\n".join(gestures_jigsaws_table(report)) + "\n", encoding="utf-8")
    return report


if __name__ == "__main__":
    main()
