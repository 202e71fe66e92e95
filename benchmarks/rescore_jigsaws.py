"""Re-score finished JIGSAWS cross-validation runs (gestures_jigsaws.py) with `--min-segment` settings,
and ensembles of them, from their raw predictions: how the offline clean-up and averaging runs change
accuracy, edit and F1@k on the development tasks, without training again.

Each fold's raw predictions come from its checkpoint (the saved network on the fold's test trials, as
``train gestures --eval-only`` runs it, before any clean-up), so runs trained with a clean-up rescore
too. ``RUN+RUN+...`` scores the ensemble of those runs: per fold, the frame probabilities of every run's
network averaged (what ``--model ensemble`` predicts from its members), on folds every run has; the runs
must have split the same trials. ``RUN@0,2`` takes members 0 and 2 of an ensemble run (``--model ensemble``:
its members in training order), their probabilities averaged. Each member trains alone, seeded by the run's
seed + its index (models/ensemble.py), so ``@0,1,2`` is what an ensemble of the first three members would
have trained and predicted; other subsets differ from one trained afresh only in their members' seeds.
Each fold's minimum segment comes from that fold's own training split exactly as ``train gestures``
computes it (``models.postprocess``); ``pN`` is the N-th percentile of the training gestures' lengths
(``auto`` is the default's percentile). Scores: pooled over all test videos
(the MS-TCN way) and averaged per video. Rows accumulate in the results file (a row of the same task, runs
and setting is replaced).

    .venv/bin/python benchmarks/rescore_jigsaws.py RUN_DIR[@MEMBERS][+RUN_DIR...]:SESSIONS_DIR:TASK ... \
        [--settings none,auto,p1,p5,1.0,g10-auto,s5-auto,o5-g10-auto]   # -> results/gestures_jigsaws_rescored.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import RESULTS, machine_info  # noqa: E402
from report_gestures import rescored_table  # noqa: E402

from midas_cli.models import metrics as M  # noqa: E402
from midas_cli.models import postprocess  # noqa: E402
from midas_cli.models.data import DatasetConfig, Normaliser, build_dataset  # noqa: E402
from midas_cli.models.sequences import sequences  # noqa: E402
from midas_cli.models.splits import Split  # noqa: E402
from midas_cli.models.train import build_model, load_checkpoint, saved_config, saved_structure  # noqa: E402

KEYS = ("accuracy", "edit", "f1@10", "f1@25", "f1@50")


def run_spec(text: str) -> tuple[Path, list[int] | None]:
    """``RUN_DIR`` or ``RUN_DIR@0,2`` (those members of an ensemble run) -> (run folder, member indices)."""
    run, at, members = text.partition("@")
    if not at:
        return Path(run), None
    try:
        indices = sorted({int(m) for m in members.split(",")})
    except ValueError:
        raise SystemExit(f"{text}: @ takes member indices, e.g. {run}@0,1,2") from None
    return Path(run), indices


def fold_data(folds: list[Path], cache: dict[str, Any], members: list[list[int] | None] | None = None,
              ) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray], float, list[str]]:
    """One fold of one or more runs: the test frame probabilities (C, T) per trial (several runs: their
    mean; ``members[i]``: those members of run i's ensemble), truths, the training labels and the model rate."""
    probs, first = [], None
    for fold, chosen in zip(folds, members or [None] * len(folds)):
        saved = load_checkpoint(fold / "checkpoint.pt")
        key = json.dumps(saved["dataset_config"], sort_keys=True)
        if key not in cache:
            cache[key] = build_dataset(cache["sessions"], DatasetConfig.from_json(saved["dataset_config"]),
                                       classes=saved["classes"])
        dataset = cache[key]
        split = Split.from_json(saved["split"])
        if first is None:
            first = (saved, dataset, split)
        elif split.units["test"] != first[2].units["test"] or saved["classes"] != first[0]["classes"]:
            raise SystemExit(f"{fold}: other test trials or classes than {folds[0]}: not an ensemble of one split")
        probs.append(test_probabilities(saved, dataset, split, chosen))
    saved, dataset, split = first  # type: ignore[misc]
    test = sequences(dataset, split.units["test"], None, list(dataset.config.modalities))
    train = [dataset.trials[dataset.trial_index(name)].labels[a:b] for name, a, b in split.units["train"]]
    mean = [np.mean([p[i] for p in probs], axis=0) for i in range(len(test.y))]
    return mean, test.y, train, dataset.trials[0].rate_hz, list(saved["classes"])


def test_probabilities(saved: dict, dataset: Any, split: Split, members: list[int] | None = None) -> list[np.ndarray]:
    """The saved network's class probabilities (C, T) on each test trial of its split, in eval mode
    (``members``: the mean of those members' probabilities, the network an ensemble)."""
    normaliser = Normaliser.from_json(saved["normaliser"]) if saved["dataset_config"]["normalise"] == "train" else None
    test = sequences(dataset, split.units["test"], normaliser, list(dataset.config.modalities))
    model, _ = build_model(saved["model"], dataset.modality_dims, len(dataset.classes), saved["model_options"],
                           *saved_structure(saved), recorded=saved_config(saved))
    model.load_state_dict(saved["state_dict"])
    model.eval()
    nets: list[Any] = [model]
    if members is not None:
        every: list[Any] = list(getattr(model, "members", []))
        if saved["model"] != "ensemble" or not set(members) <= set(range(len(every))):
            raise SystemExit(f"members {members}: not members of this {saved['model']} run")
        nets = [every[i] for i in members]
    with torch.no_grad():
        out = []
        for x in test.x:
            xt, mask = torch.from_numpy(x.T[None]), torch.ones(1, len(x), dtype=torch.bool)
            out.append(np.mean([torch.softmax(net.frame_logits(net(xt, mask))[0], dim=0).numpy() for net in nets], axis=0))
        return out


def min_frames(setting: str, train: list[np.ndarray], rate: float) -> int:
    """``--min-segment`` ``setting``'s minimum, or ``pN``'s: the N-th percentile of the gesture lengths."""
    if not setting.startswith("p"):
        return postprocess.min_frames(setting, train, rate)
    lengths = [length for y in train for cls, length in postprocess._runs(y) if cls >= 0]
    return int(np.floor(np.percentile(lengths, float(setting[1:])))) if lengths else 0


def split_lag(setting: str) -> tuple[int | None, str]:
    """``oL-DECODING`` -> (L, DECODING); any other setting -> (None, setting). ValueError where L is not a
    whole number of frames or what follows is not a decoding (``v``, ``g``, ``s``)."""
    if setting[:1] != "o":
        return None, setting
    lag, _, decoding = setting[1:].partition("-")
    if not lag.isdigit() or decoding[:1] not in ("v", "g", "s"):
        raise ValueError(f"setting {setting!r}: oL- takes a lag in frames and a decoding, e.g. o5-g10-auto")
    return int(lag), decoding


def clean_up(setting: str, probs: list[np.ndarray], train: list[np.ndarray], rate: float, n_classes: int,
             minima: list[int]) -> list[np.ndarray]:
    """One fold's predictions under ``setting``: a ``--min-segment`` setting (the greedy merge), ``v-S`` (the
    exact minimum-length decoding at setting S), ``gW-S`` (the same with the training order of gestures,
    weight W) or ``gW+S`` (decoded with that order and no minimum, then merged at S); ``sP-S``, ``sP+S``: any
    order, each change of gesture costs P (nats). ``oL-`` before a decoding (``o5-g10-auto``): decoded as a
    live decoder lagging L frames would (``postprocess.decode_online``: frame t labelled at t + L)."""
    lag, setting = split_lag(setting)
    then_merge = setting[:1] in "vgs" and "+" in setting
    decoder, _, minimum_setting = setting.rpartition("+" if then_merge else "-") if setting[:1] in "vgs" \
        else ("", "", setting)
    minimum = min_frames(minimum_setting, train, rate)
    minima.append(minimum)
    if not decoder:
        return [postprocess.merge_short_segments(p.argmax(axis=0), minimum) for p in probs]
    weight = 0.0 if decoder == "v" else float(decoder[1:])
    trans = postprocess.switch_scores(train, n_classes, weight) if decoder[0] == "g" else \
        (np.full((n_classes, n_classes), -weight) if weight else None)  # what train gestures --grammar W uses
    decoded = [postprocess.decode_online(np.log(np.maximum(p, 1e-12)), 0 if then_merge else minimum, trans, lag)
               for p in probs]
    return [postprocess.merge_short_segments(d, minimum) for d in decoded] if then_merge else decoded


def rescore(run_dirs: list[Path], sessions: list[Path], settings: list[str],
            members: list[list[int] | None] | None = None) -> list[dict[str, Any]]:
    """One row per setting: pooled and per-video figures over the folds every run finished (``members``:
    per run, the ensemble members taken, None for the whole network)."""
    cache: dict[str, Any] = {"sessions": sessions}
    names = sorted(f.name for f in run_dirs[0].glob("fold-*") if (f / "metrics.json").is_file())
    names = [n for n in names if all((r / n / "metrics.json").is_file() for r in run_dirs)]
    folds = [fold_data([r / n for r in run_dirs], cache, members) for n in names]
    labels = [str(r) + (f"@{','.join(map(str, m))}" if m is not None else "")
              for r, m in zip(run_dirs, members or [None] * len(run_dirs))]
    rows = []
    for setting in settings:
        preds, truths, minima = [], [], []
        for fold_probs, fold_truths, train, rate, classes in folds:
            preds += clean_up(setting, fold_probs, train, rate, len(classes), minima)
            truths += fold_truths
        classes = folds[0][4]
        pooled = M.evaluate(preds, truths, classes)["summary"]
        videos = [M.evaluate([p], [t], classes)["summary"] for p, t in zip(preds, truths)]
        rows.append({"run_dir": " + ".join(labels), "setting": setting, "folds": len(folds),
                     "videos": len(preds), "min_segment_frames": minima, "pooled": {k: pooled[k] for k in KEYS},
                     "per_video": {k: float(np.mean([v[k] for v in videos])) for k in KEYS}})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="RUN_DIR[@MEMBERS][+RUN_DIR...]:SESSIONS_DIR:TASK (the sessions the "
                        "runs trained on; several runs: their ensemble; @0,2: those members of an ensemble run)")
    parser.add_argument("--settings", default="none,auto,p5,1.0,1.5,2.0")
    args = parser.parse_args()
    torch.set_num_threads(1)  # a shared machine: many threads waiting on each other cost far more than they give
    for setting in args.settings.split(","):
        try:
            _, decoding = split_lag(setting)
        except ValueError as exc:
            parser.error(str(exc))
        if decoding[:1] in ("v", "g", "s") and not {"-", "+"} & set(decoding):
            parser.error(f"setting {setting!r}: a decoding needs its minimum, e.g. {decoding}-auto")
    rows = []
    for spec in args.runs:
        run_dirs, sessions_dir, task = spec.split(":")
        sessions = sorted(p for p in Path(sessions_dir).iterdir() if (p / "manifest.json").is_file())
        runs, members = zip(*[run_spec(r) for r in run_dirs.split("+")])
        rows += [{"task": task, **row} for row in rescore(list(runs), sessions, args.settings.split(","), list(members))]
        print(f"rescore: {task} {run_dirs} done", file=sys.stderr, flush=True)
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / "gestures_jigsaws_rescored.json"
    key = lambda row: (row["task"], row["run_dir"], row["setting"])  # noqa: E731
    new = {key(row) for row in rows}
    kept = [row for row in json.loads(path.read_text(encoding="utf-8"))["rows"] if key(row) not in new] \
        if path.is_file() else []
    path.write_text(json.dumps({"machine": machine_info(), "rows": kept + rows}, indent=2) + "\n", encoding="utf-8")
    print("\n".join(rescored_table(rows)))


if __name__ == "__main__":
    main()
