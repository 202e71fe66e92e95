"""Training epoch time / peak memory of MS-TCN++ and the transformer on CPU on the simulated Raven-II
dataset, and online inference latency.

Data: `midas simulate dataset --platform raven-ii --trials 15 --seed 1` (peg transfer, full-length
trials) and `midas align` of every session, both through the CLI and timed (the data preparation a user
pays once). Then each (model, number of trials) case runs in its own subprocess (peak memory = that
process's VmHWM, which includes building the dataset): the first N sessions (sorted by name) go through
``models.data.build_dataset`` (emht, mtm, psm and image modalities; pos, ori, vel and grasper feature
sets; Raven-II's 10 Hz as in the paper), are normalised over all their frames and trained as whole
trials with the real training loop (``models.train.fit``: Adam, batch size 4, no validation), timed
over the epochs after one warm-up epoch. Online inference: one forward pass per new frame over a
trailing context (the transformer's 64-frame window; 1024 frames for MS-TCN++), batch 1, one torch
thread, ``torch.no_grad``, 100 calls. Sizes 5, 10 and 15 trials give the slope per 1000 frames.

    .venv/bin/python benchmarks/bench_train.py            # 15 trials; 5, 10, 15 -> results/train.json
    .venv/bin/python benchmarks/bench_train.py --quick    # 3 trials cut to 40 s; 2 and 3
    .venv/bin/python benchmarks/bench_train.py --louo     # JIGSAWS-sized LOUO fold -> results/train_louo.json
    nice -n 19 .venv/bin/python benchmarks/bench_train.py --louo-all [--epochs N]   # Suturing-sized, all 8 folds

LOUO (``--louo``): a JIGSAWS-sized dataset, 8 subjects x 5 trials of ~100 s at 30 Hz (``midas simulate
dataset --platform raven-ii --trials 40 --subjects 8 --max-seconds 100``, ``--difficulty real``), 76 input
columns as JIGSAWS's kinematics: mtm + psm, both arms, pos 3 + rotation matrix 9 + linear velocity 3 +
angular velocity 3 + grasper 1 per arm, at ``--model-rate 30``. One LOUO fold of MS-TCN++ as
``train gestures --split louo`` runs it today (fold 0: 7 subjects train, no validation set, 1 test; the
MS-TCN++ recipe: batch 1, ``RECIPES["mstcn"]["epochs"]`` epochs) through the real loop
(``models.train.fit``): a warm-up epoch, then ``LOUO_EPOCHS`` timed epochs; the whole fold is
extrapolated (recipe epochs x epoch + test evaluation) and said so.
CPU only here; a GPU run is recorded only where ``torch.cuda.is_available()``.

Whole cross-validation, Suturing-sized (``--louo-all``, issue 27's time budget: <= 30 min on 2 CPU cores at
the defaults): 38 trials of ~100 s over 8 subjects (JIGSAWS Suturing: 38 labelled trials, 8 users, ~3,000
frames at 30 Hz each), simulated and aligned as above, then ``midas train gestures SESSIONS --modalities
mtm,psm --split louo --fold all --no-baseline --jobs 2`` through the CLI, everything else at its defaults
(features, model rate, recipe; ``--epochs N`` overrides the recipe, to see what fewer epochs would save):
measured, not extrapolated. The wall time, each fold's own time (the run's done markers) and the load are
recorded in ``results/train_louo_all[-MODEL].json`` (``--epochs``: ``-e<N>``; MODEL when it is not MS-TCN++); the accuracy on
simulated data is kept but means nothing for the real task.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load_average, machine_info, write_result  # noqa: E402

PLATFORM, SEED = "raven-ii", 1
MODALITIES = ("emht", "mtm", "psm", "image")
FEATURES = ("pos", "ori", "vel", "grasper")
ONLINE_CONTEXT = {"mstcn": 1024, "transformer": 64}
LOUO_SUBJECTS, LOUO_TRIALS_PER_SUBJECT, LOUO_EPOCHS = 8, 5, 2
LOUO_MODALITIES, LOUO_RATE_HZ, LOUO_MAX_SECONDS = ("mtm", "psm"), 30.0, 100.0
LOUO_FEATURES = ("pos", "ori", "vel", "angvel", "grasper")  # with rotation matrices: JIGSAWS's 19 per arm


def prepare_dataset(folder: Path, trials: int, max_seconds: float | None, subjects: int = 1, jobs: int = 2) -> dict:
    """Simulate and align ``trials`` sessions into ``folder`` through the CLI (``jobs`` processes); wall times and sizes."""
    limit = ["--max-seconds", str(max_seconds)] if max_seconds else []
    t0 = time.monotonic()
    made = _cli("simulate", "dataset", "--platform", PLATFORM, "--trials", str(trials), "--seed", str(SEED),
                "--subjects", str(subjects), "--out", str(folder), "--jobs", str(jobs), "--json", *limit)
    simulate_s = time.monotonic() - t0
    sessions = [r["path"] for r in json.loads(made)]
    t0 = time.monotonic()
    aligned = json.loads(_cli("align", *sessions, "--jobs", str(jobs), "--json"))
    align_s = time.monotonic() - t0
    size = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
    return {"platform": PLATFORM, "seed": SEED, "trials": trials, "subjects": subjects,
            "max_seconds_per_trial": max_seconds,
            "simulate_s": round(simulate_s, 2), "align_s": round(align_s, 2), "jobs": jobs,
            "video_frames_total": int(sum(a["frames"] for a in aligned)), "dataset_mb": round(size / 1e6, 1)}


def _cli(*args: str, show: bool = False) -> str:
    """midas ARGS' stdout; ``show``: its stderr (the progress lines) passes through to ours as it runs."""
    proc = subprocess.run([sys.executable, "-m", "midas_cli", *args], stdout=subprocess.PIPE,
                          stderr=None if show else subprocess.PIPE, text=True)
    if proc.returncode != 0:
        said = "see its stderr above" if show else proc.stderr[-2000:]
        raise RuntimeError(f"midas {' '.join(args[:2])} failed ({proc.returncode}): {said}")
    return proc.stdout


def sessions_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if (p / "manifest.json").is_file())


def case(model_name: str, folder: Path, n_trials: int, epochs: int) -> dict:
    """Runs inside the child: build the dataset, time ``epochs`` epochs after a warm-up, then online inference."""
    import torch

    from midas_cli.models.data import DatasetConfig, build_dataset
    from midas_cli.models.sequences import Sequences
    from midas_cli.models.train import TrainConfig, build_model, fit

    torch.manual_seed(0)
    t0 = time.monotonic()
    dataset = build_dataset(sessions_in(folder)[:n_trials], DatasetConfig(MODALITIES, FEATURES))
    build_s = time.monotonic() - t0
    seqs, empty = whole_trials(dataset), Sequences([], [], [])
    model, _ = build_model(model_name, dataset.modality_dims, len(dataset.classes), {})
    fit(model, seqs, empty, TrainConfig(model=model_name, epochs=1), torch.device("cpu"))  # warm-up
    t0 = time.monotonic()
    fit(model, seqs, empty, TrainConfig(model=model_name, epochs=epochs), torch.device("cpu"))
    epoch_s = (time.monotonic() - t0) / epochs
    frames = [len(y) for y in seqs.y]
    return {"model": model_name, "trials": len(frames), "frames_total": int(sum(frames)),
            "frames_per_trial_mean": round(float(np.mean(frames)), 1), "rate_hz": dataset.trials[0].rate_hz,
            "modality_dims": dataset.modality_dims, "classes": len(dataset.classes),
            "dataset_build_s": round(build_s, 2), "epoch_s": round(epoch_s, 3), "timed_epochs": epochs,
            "torch_threads": torch.get_num_threads(),
            "online": online_latency(model, seqs.x[0].shape[1], ONLINE_CONTEXT[model_name])}


def whole_trials(dataset):  # noqa: ANN001, ANN201 - GestureDataset -> Sequences
    """Every trial as one training unit, normalised over all frames (the loop's input: (T, D) float32)."""
    from midas_cli.models.data import Normaliser
    from midas_cli.models.sequences import Sequences

    order = list(dataset.config.modalities)
    blocks = [t.stacked(order) for t in dataset.trials]
    normaliser = Normaliser.fit(blocks)
    return Sequences([(t.name, 0, len(t.labels)) for t in dataset.trials], [normaliser.apply(b) for b in blocks],
                     [t.labels for t in dataset.trials])


def online_latency(model, dim: int, context: int, calls: int = 100) -> dict:  # noqa: ANN001
    import torch

    model.eval()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one frame at a time beside a recorder: no OpenMP team to wake (or wait for)
    x, mask = torch.randn(1, dim, context), torch.ones(1, context, dtype=torch.bool)
    times = []
    with torch.no_grad():
        for _ in range(calls + 5):
            t0 = time.perf_counter()
            model.frame_logits(model(x, mask))[0, :, -1].argmax()
            times.append((time.perf_counter() - t0) * 1e3)
    torch.set_num_threads(threads)
    ms = np.array(times[5:])
    return {"context_frames": context, "torch_threads": 1, "p50_ms": round(float(np.percentile(ms, 50)), 3),
            "p99_ms": round(float(np.percentile(ms, 99)), 3), "max_ms": round(float(ms.max()), 3)}


def run_child(model_name: str, folder: Path, n_trials: int, epochs: int) -> dict:
    load = load_average()
    proc = subprocess.run([sys.executable, __file__, "--case", model_name, str(folder), str(n_trials), str(epochs)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"case {model_name} x {n_trials} trials failed: {proc.stderr[-2000:]}")
    return {"load_average_before_after": [load, load_average()], **json.loads(proc.stdout.strip().splitlines()[-1])}


def slopes(runs: list[dict]) -> dict:
    """Per model: least-squares epoch seconds and peak MiB per 1000 training frames, over the sizes."""
    out = {}
    for model in sorted({r["model"] for r in runs}):
        rs = [r for r in runs if r["model"] == model]
        if len(rs) >= 2:
            k = np.array([r["frames_total"] for r in rs]) / 1000.0
            out[model] = {"epoch_s_per_1000_frames": round(float(np.polyfit(k, [r["epoch_s"] for r in rs], 1)[0]), 4),
                          "peak_mib_per_1000_frames": round(float(np.polyfit(k, [r["peak_rss_mib"] for r in rs], 1)[0]), 2)}
    return out


def louo_case(folder: Path, device_name: str) -> dict:
    """Runs inside the child: one LOUO fold of MS-TCN++ on ``device_name`` (see the module docstring)."""
    import torch

    from midas_cli.models.data import DatasetConfig, build_dataset
    from midas_cli.models.splits import make_split
    from midas_cli.models.sequences import fit_normaliser, sequences
    from midas_cli.models.train import RECIPES, TrainConfig, build_model, fit, predict

    torch.manual_seed(0)
    device = torch.device(device_name)
    t0 = time.monotonic()
    dataset = build_dataset(sessions_in(folder), DatasetConfig(LOUO_MODALITIES, LOUO_FEATURES, rate_hz=LOUO_RATE_HZ))
    build_s = time.monotonic() - t0
    split = make_split(dataset, "louo", 0, 0)  # the default: no validation set, every other subject trains
    order = list(dataset.config.modalities)
    normaliser = fit_normaliser(dataset, split.units["train"], order)
    parts = {part: sequences(dataset, units, normaliser, order) for part, units in split.units.items()}
    model, _ = build_model("mstcn", dataset.modality_dims, len(dataset.classes), {})
    model.to(device)
    fit(model, parts["train"], parts["val"], TrainConfig(model="mstcn", epochs=1), device)  # warm-up
    t0 = time.monotonic()
    fit(model, parts["train"], parts["val"], TrainConfig(model="mstcn", epochs=LOUO_EPOCHS), device)
    epoch_s = (time.monotonic() - t0) / LOUO_EPOCHS
    fold_epochs = RECIPES["mstcn"]["epochs"]
    t0 = time.monotonic()
    predict(model, parts["test"], device)
    test_s = time.monotonic() - t0
    frames = {part: int(sum(len(y) for y in seqs.y)) for part, seqs in parts.items()}
    return {"device": device_name, "torch_threads": torch.get_num_threads(), "columns": sum(dataset.modality_dims.values()),
            "modality_dims": dataset.modality_dims, "rate_hz": LOUO_RATE_HZ, "classes": len(dataset.classes),
            "trials": {part: len(units) for part, units in split.units.items()}, "frames": frames,
            "frames_per_trial_mean": round(float(np.mean([len(t.labels) for t in dataset.trials])), 1),
            "dataset_build_s": round(build_s, 2), "timed_epochs": LOUO_EPOCHS, "epoch_s": round(epoch_s, 2),
            "test_predict_s": round(test_s, 2), "fold_epochs": fold_epochs, "batch_size": RECIPES["mstcn"]["batch_size"],
            "fold_s_extrapolated": round(fold_epochs * epoch_s + test_s, 1)}


LOUO_ALL_TRIALS = 38  # JIGSAWS Suturing's labelled trials


def run_louo_all(epochs: int | None, quick: bool, accelerator: str = "cpu", prep_jobs: int = 2) -> None:
    """Simulate a Suturing-shaped dataset and time a whole LOUO cross-validation at the defaults (module docs);
    ``accelerator`` cuda: ``--accelerator cuda`` (the folds batched in one process, ``--fold-batch auto``)."""
    from gestures_jigsaws import fold_seconds, torch_facts

    trials, seconds = (LOUO_SUBJECTS * 2, 15.0) if quick else (LOUO_ALL_TRIALS, LOUO_MAX_SECONDS)
    with tempfile.TemporaryDirectory(prefix="midas-bench-louo-all-") as tmp:
        sessions, out = Path(tmp) / "sessions", Path(tmp) / "run"
        print(f"train: simulating and aligning {trials} {PLATFORM} trials ({LOUO_SUBJECTS} subjects) ...", file=sys.stderr)
        load = load_average()
        data = {**prepare_dataset(sessions, trials, seconds, LOUO_SUBJECTS, prep_jobs),
                "load_average_before_after": [load, load_average()]}
        args = ["train", "gestures", str(sessions), "--modalities", ",".join(LOUO_MODALITIES), "--split", "louo",
                "--fold", "all", "--no-baseline", "--out", str(out), "--json"]
        args += ["--jobs", "2"] if accelerator == "cpu" else ["--accelerator", accelerator]
        args += ["--epochs", str(epochs)] if epochs is not None else []
        print(f"train: {' '.join(args[:2])} --split louo --fold all (the default model and recipe"
              f"{f', {epochs} epochs' if epochs is not None else ''}) ...", file=sys.stderr)
        load, t0 = load_average(), time.monotonic()
        _cli(*args, show=True)
        wall = time.monotonic() - t0
        first = json.loads((out / "fold-0" / "run.json").read_text(encoding="utf-8"))
        cv = json.loads((out / "cv.json").read_text(encoding="utf-8"))
        run = {"wall_s": round(wall, 1), "load_average_before_after": [load, load_average()],
               "command": "midas " + " ".join(a if not a.startswith(tmp) else "…" for a in args),
               "model": first["model"], "fold_seconds": fold_seconds(out, first["model"]),
               "folds": len(cv.get("folds", [])) or None,
               "epochs": first["train_config"]["epochs"] or "+".join(str(m["epochs"]) for m in first["recipe"]["members"]),
               "recipe": first["recipe"],
               "rate_hz": first["trials"][0]["rate_hz"], "inputs": {m: len(v) for m, v in first["feature_names"].items()},
               "frames_at_model_rate": int(sum(t["frames"] for t in first["trials"])),
               "trials": len(first["trials"]), "simulated_accuracy": cv.get("pooled", {}).get("accuracy"),
               "git_commit": first.get("code", {}).get("git_commit")}
    # one file per model and epochs (MS-TCN++'s runs, from before the ensemble was the default, keep their names)
    name = "train_louo_all" + (f"-{run['model']}" if run["model"] != "mstcn" else "") + (f"-e{epochs}" if epochs else "")
    name += f"-{accelerator}" if accelerator != "cpu" else ""
    facts = torch_facts(2 if accelerator == "cpu" else 1)
    write_result(name, {"machine": {**machine_info(), **facts}, "quick": quick, "data": data, "run": run})


def run_louo() -> None:
    import torch

    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    with tempfile.TemporaryDirectory(prefix="midas-bench-louo-") as tmp:
        trials = LOUO_SUBJECTS * LOUO_TRIALS_PER_SUBJECT
        print(f"train: simulating and aligning {trials} {PLATFORM} trials ({LOUO_SUBJECTS} subjects) ...", file=sys.stderr)
        load = load_average()
        data = {**prepare_dataset(Path(tmp), trials, LOUO_MAX_SECONDS, LOUO_SUBJECTS),
                "load_average_before_after": [load, load_average()]}
        runs = []
        for device in devices:
            print(f"train: LOUO fold 0, mstcn on {device} ...", file=sys.stderr)
            load = load_average()
            proc = subprocess.run([sys.executable, __file__, "--louo-case", tmp, device], capture_output=True, text=True)
            if proc.returncode != 0:
                raise RuntimeError(f"LOUO case on {device} failed: {proc.stderr[-2000:]}")
            runs.append({"load_average_before_after": [load, load_average()],
                         **json.loads(proc.stdout.strip().splitlines()[-1])})
    write_result("train_louo", {"machine": machine_info(), "data": data, "gpu_available": len(devices) > 1,
                                "dataset_config": {"modalities": list(LOUO_MODALITIES), "features": list(LOUO_FEATURES)},
                                "runs": runs})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 trials cut to 40 s; sizes 2 and 3")
    parser.add_argument("--louo", action="store_true", help="JIGSAWS-sized LOUO fold timing -> results/train_louo.json")
    parser.add_argument("--louo-all", action="store_true",
                        help="Suturing-sized whole LOUO cross-validation at the defaults -> results/train_louo_all.json")
    parser.add_argument("--epochs", type=int, default=None, help="--louo-all: override the recipe's epochs")
    parser.add_argument("--accelerator", choices=("cpu", "cuda"), default="cpu",
                        help="--louo-all: train on this (cuda: the folds batched in one process; result name -cuda)")
    parser.add_argument("--prep-jobs", type=int, default=2, help="--louo-all: processes to simulate and align with")
    parser.add_argument("--case", nargs=4, help=argparse.SUPPRESS)
    parser.add_argument("--louo-case", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.louo_case:
        print(json.dumps(louo_case(Path(args.louo_case[0]), args.louo_case[1])))
        return
    if args.louo:
        run_louo()
        return
    if args.louo_all:
        run_louo_all(args.epochs, args.quick, args.accelerator, args.prep_jobs)
        return
    if args.case:
        result = case(args.case[0], Path(args.case[1]), int(args.case[2]), int(args.case[3]))
        hwm = [line for line in open("/proc/self/status") if line.startswith("VmHWM:")][0].split()[1]
        print(json.dumps({**result, "peak_rss_mib": round(int(hwm) / 1024, 1)}))
        return
    trials, max_seconds, sizes, epochs = (3, 40.0, [2, 3], 1) if args.quick else (15, None, [5, 10, 15], 2)
    with tempfile.TemporaryDirectory(prefix="midas-bench-train-") as tmp:
        print(f"train: simulating and aligning {trials} {PLATFORM} trials ...", file=sys.stderr)
        load = load_average()
        data = {**prepare_dataset(Path(tmp), trials, max_seconds), "load_average_before_after": [load, load_average()]}
        runs = []
        for model_name in ("mstcn", "transformer"):
            for n in sizes:
                print(f"train: {model_name}, {n} trials ...", file=sys.stderr)
                runs.append(run_child(model_name, Path(tmp), n, epochs))
    write_result("train", {"machine": machine_info(), "quick": args.quick, "data": data,
                           "dataset_config": {"modalities": list(MODALITIES), "features": list(FEATURES)},
                           "timed_epochs": epochs, "runs": runs, "slopes": slopes(runs)})


if __name__ == "__main__":
    main()
