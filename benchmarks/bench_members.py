"""What each member of the default ensemble costs to train: CPU seconds of one epoch of MS-TCN++ and of
the transformer, on the same fold of real data, interleaved, one torch thread.

A whole-run wall time on a shared machine moves with the host's load by more than one member's share
(BENCHMARKS.md, the Suturing-sized LOUO rows), so the share is measured here on its own: the process's CPU
time (``time.process_time``) of one epoch through the real loop (``models.train.fit``, each model's recipe:
batch size, lr, shifted inputs), the two models alternating ``--reps`` times (a new seed each), the median
taken. A member's cost is then its recipe's epochs x its epoch; the ensemble's the sum over its members
(``models/ensemble.py`` ``MEMBERS``), against the four-member ensemble of before.

Data: a fold of a JIGSAWS development task as ``gestures_jigsaws.py`` imported it (its ``--work`` folder),
with the inputs the CLI picks for robot data (mtm + psm pos, vel, angvel, grasper; 10 Hz).

    .venv/bin/python benchmarks/bench_members.py [--task knot_tying] [--fold 0] [--reps 3]
        # -> results/ensemble_members.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import machine_info, write_result  # noqa: E402

from midas_cli.models.data import DatasetConfig, build_dataset  # noqa: E402
from midas_cli.models.ensemble import MEMBERS  # noqa: E402
from midas_cli.models.train import RECIPES, TrainConfig, fit, prepare_fold, seeded_model  # noqa: E402

WORK = Path("/tmp/midas-jigsaws-dev")  # gestures_jigsaws.py's default --work
FOUR = ("mstcn", "transformer", "mstcn", "transformer")  # the default until 2026-11-28


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=WORK, help="gestures_jigsaws.py's work folder")
    parser.add_argument("--task", default="knot_tying")
    parser.add_argument("--fold", type=int, default=0)
    parser.add_argument("--reps", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    sessions = sorted(p for p in (args.work / "sessions" / args.task).iterdir() if (p / "manifest.json").is_file())
    dataset = build_dataset(sessions, DatasetConfig(modalities=("mtm", "psm"), features=("pos", "vel", "angvel", "grasper")))
    seconds: dict[str, list[float]] = {"mstcn": [], "transformer": []}
    for rep in range(args.reps):
        for name in seconds:
            config = TrainConfig(model=name, split="louo", fold=args.fold, epochs=1, seed=rep, selection="last").resolved()
            fold = prepare_fold(dataset, config)
            model, _ = seeded_model(dataset, config)
            start = time.process_time()
            fit(model, fold.parts["train"], fold.parts["val"], config, torch.device("cpu"), augment=fold.augment)
            seconds[name].append(round(time.process_time() - start, 3))
            print(f"members: {name} epoch {rep + 1}: {seconds[name][-1]:.2f} CPU s", file=sys.stderr, flush=True)
    epoch = {name: statistics.median(values) for name, values in seconds.items()}
    member = {name: RECIPES[name]["epochs"] * epoch[name] for name in epoch}
    now, before = sum(member[m] for m in MEMBERS), sum(member[m] for m in FOUR)
    write_result("ensemble_members", {
        "machine": machine_info(), "torch": torch.__version__, "task": args.task, "fold": args.fold,
        "train_frames": int(sum(len(y) for y in fold.parts["train"].y)), "epoch_cpu_s": seconds,
        "epoch_median_cpu_s": epoch, "member_cpu_s": member, "members": list(MEMBERS), "ensemble_cpu_s": now,
        "four_members_cpu_s": before, "ratio_to_four": now / before})


if __name__ == "__main__":
    main()
