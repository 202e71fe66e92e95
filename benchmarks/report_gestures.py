"""BENCHMARKS.md: gesture recognition on the JIGSAWS development tasks, from results/gestures_jigsaws.json
(gestures_jigsaws.py); used by report.py and by the benchmark itself (results/gestures_jigsaws.md)."""

from __future__ import annotations

import json
from typing import Any

TITLES = {"baseline": "baseline (per-frame logistic regression)", "mstcn": "MS-TCN++", "transformer": "transformer",
          "ensemble": "ensemble (MS-TCN++ and transformers: *epochs* lists its members)"}
ORDER = ("baseline", "mstcn", "transformer", "ensemble")


def _pct(value: float) -> str:
    return f"{100 * value:.1f}"


def _span(low: float, high: float) -> str:
    """Seconds as a range in s (under two minutes) or min."""
    return f"{low:.0f}–{high:.0f} s" if high < 120 else f"{low / 60:.1f}–{high / 60:.1f} min"


def _minutes(row: dict[str, Any]) -> str:
    """Wall time of the run that trained the row, and the span of its folds' own training times."""
    t, secs = row["timing"], list((row.get("fold_seconds") or {}).values())
    folds = f"; a fold {_span(min(secs), max(secs))}" if secs else ""
    if row["trained_in"] != row["model"]:
        return f"in the {TITLES[row['trained_in']]} run{folds}"
    if t.get("wall_s") is None:
        return f"unfinished (started {t.get('started') or '?'}, --jobs {t.get('jobs') or '?'}){folds}"
    resumed = " (resumed: later folds only)" if t.get("resumed") else ""
    resumed += f" ({t['wall_from']})" if t.get("wall_from") else ""
    load = "–".join(f"{x:g}" for x in t.get("load_average_before_after") or [])
    return f"{t['wall_s'] / 60:.1f} min, --jobs {t['jobs']}{resumed}{folds}{f'; load {load}' if load else ''}"


def _title(row: dict[str, Any], rows: list[dict[str, Any]]) -> str:
    """The model's title; a variant's name and its extra train options after it; a causal row's says so,
    with its pooled accuracy minus the offline row's (:func:`offline_partner`): raw against raw at the last
    epoch both learning curves have, else the rows' own figures (same epochs)."""
    title = TITLES[row["model"]]
    if row.get("variant"):
        title += f" [{row['variant']}: `{row['train_args']}`]"
    if not row.get("causal"):
        return title
    offline = offline_partner(row, rows)
    delta = ""
    if offline is not None and row.get("curve") and offline.get("curve"):  # both raw (a causal run has no clean-up)
        deltas = curve_deltas(row["curve"], offline["curve"])
        if deltas:
            epoch, diff = deltas[-1]
            delta = f"; acc {100 * diff:+.1f} vs offline, raw, epoch {epoch}"
    elif offline is not None:
        delta = f"; acc {100 * (row['pooled']['accuracy'] - offline['pooled']['accuracy']):+.1f} vs offline"
    return f"{title} (causal{delta})"


def offline_partner(row: dict[str, Any], rows: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The offline row a causal ``row`` is compared with: the same model (and task), not causal, the same
    variant or else the same inputs, trained with the same options but the causal ones (PARTNER_IGNORES:
    a shifted-input causal run against the offline run with shifted inputs); where ``row`` has a learning
    curve, one with a curve sharing an epoch on the same folds (any epochs option: the curve's epochs say
    what is compared), else the same epochs option. The same variant first, then the curve that shares the most epochs."""
    def shares_epochs(r: dict[str, Any]) -> bool:
        if row.get("curve") and r.get("curve"):
            return bool(curve_deltas(row["curve"], r["curve"]))
        return r["epochs_option"] == row["epochs_option"]

    found = [r for r in rows if r["model"] == row["model"] and not r.get("causal") and r["task"] == row["task"]
             and (r.get("variant") == row.get("variant") or _same_inputs(r.get("inputs"), row.get("inputs")))
             and _trained_alike(r, row) and shares_epochs(r)]
    found.sort(key=lambda r: (r.get("variant") != row.get("variant"), not (row.get("curve") and r.get("curve")),
                              -len(curve_deltas(row["curve"], r["curve"])) if row.get("curve") and r.get("curve") else 0))
    return found[0] if found else None


def common_folds(mine: dict[str, Any], theirs: dict[str, Any]) -> list[str] | None:
    """The folds (held-out groups) two learning curves both have; None where a curve predates ``by_fold``."""
    if "by_fold" not in mine or "by_fold" not in theirs:
        return None
    return sorted(set(mine["by_fold"]) & set(theirs["by_fold"]))


def curve_deltas(mine: dict[str, Any], theirs: dict[str, Any]) -> list[tuple[int, float]]:
    """(epoch, accuracy difference) at every epoch both learning curves have, in order, pooled over the
    folds both have (an unfinished run against a finished one: its folds only). Curves without
    ``by_fold`` are compared only when they pool as many folds (else nothing: not like with like)."""
    folds = common_folds(mine, theirs)
    if folds is None:
        if mine.get("folds") != theirs.get("folds"):
            return []
        at = dict(zip(theirs["epochs"], theirs["accuracy"]))
        return [(e, a - at[e]) for e, a in zip(mine["epochs"], mine["accuracy"]) if e in at]

    def pooled(curve: dict[str, Any], epoch: int) -> float | None:
        points = [curve["by_fold"][f].get(str(epoch)) for f in folds]
        if any(p is None for p in points):
            return None
        return sum(p[0] for p in points) / max(1, sum(p[1] for p in points))

    out = []
    for epoch in sorted(set(mine["epochs"]) | set(theirs["epochs"])):
        a, b = pooled(mine, epoch), pooled(theirs, epoch)
        if a is not None and b is not None:
            out.append((epoch, a - b))
    return out if folds else []


def causal_table(rows: list[dict[str, Any]]) -> list[str]:
    """Causal runs with learning curves against their offline partner's, epoch by epoch (raw pooled accuracy)."""
    pairs = [(r, offline_partner(r, rows)) for r in rows if r.get("causal") and r.get("curve")]
    pairs = [(r, o) for r, o in pairs if o is not None and o.get("curve")]
    if not pairs:
        return []
    out = ["What the causal models cost, from the learning curves (raw pooled accuracy %, causal − offline of the "
           "same inputs, at each epoch both were scored; a delayed model (`--delay`) labels frame t from the frames up "
           "to t + delay), pooled over the folds both runs have:", "",
           "| task | causal run | offline run | folds | causal − offline, by epoch |", "|---|---|---|---|---|"]
    for r, o in pairs:
        cells = ", ".join(f"{e}: {100 * d:+.1f}" for e, d in curve_deltas(r["curve"], o["curve"]))
        folds = common_folds(r["curve"], o["curve"])
        shared = " ".join(folds) if folds is not None else f"{r['curve'].get('folds', '?')} (both)"
        out.append(f"| {r['task']} | {_title(r, rows).split(' (causal')[0]} | {_title(o, rows)} | {shared} | {cells} |")
    return out + [""]


# --train-args options left out when a causal run looks for its offline partner: the causal ones, the
# learning curve's (it does not change the weights), and the inputs' (compared by _same_inputs)
PARTNER_IGNORES = ("--delay", "--curve-every", "--modalities", "--features", "--model-rate", "--sides")


def _trained_alike(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Two runs trained the same way but for the causal options, the epochs and the clean-up: by the
    settings ``train gestures`` resolved (the rows' ``training``, defaults included) where both rows have
    them, else by their ``--train-args`` (rows from before ``training``: a default that changed between
    them goes unseen)."""
    if a.get("training") and b.get("training"):
        def kept(settings: dict[str, Any]) -> dict[str, Any]:
            return {k: v for k, v in settings.items() if k not in RESOLVED_IGNORES}
        return kept(a["training"]) == kept(b["training"])
    return _training_options(a.get("train_args", "")) == _training_options(b.get("train_args", ""))


RESOLVED_IGNORES = ("causal", "delay_s", "curve_every", "epochs", "min_segment", "grammar")


def _training_options(train_args: str) -> list[str]:
    """A run's ``--train-args`` without ``--causal`` and the PARTNER_IGNORES options (and their values)."""
    kept: list[str] = []
    skip = False
    for word in train_args.split():
        if skip:
            skip = False
        elif word in PARTNER_IGNORES:
            skip = True
        elif word != "--causal" and not word.startswith(tuple(f"{o}=" for o in PARTNER_IGNORES)):
            kept.append(word)
    return kept


def _same_inputs(a: dict[str, Any] | None, b: dict[str, Any] | None) -> bool:
    """The same modalities, features and sides, and rates equal or one left to the CLI's default (None)."""
    if not a or not b:
        return a == b
    keys = ("modalities", "features", "sides")
    return all(a.get(k) == b.get(k) for k in keys) and (None in (a.get("rate_hz"), b.get("rate_hz"))
                                                          or a.get("rate_hz") == b.get("rate_hz"))


def _meets(row: dict[str, Any], target_accuracy: float, target_edit: float) -> str:
    if row["missing_folds"]:
        return "— (not all folds)"
    ok = row["pooled"]["accuracy"] >= target_accuracy and row["pooled"]["edit"] >= target_edit
    return "yes" if ok else "no"


def gestures_jigsaws_table(report: dict[str, Any]) -> list[str]:
    """One table per task: pooled and per-video figures, fold spread, per-fold accuracy, wall time."""
    out: list[str] = []
    for name, task in report["tasks"].items():
        rows = sorted((r for r in report["rows"] if r["task"] == name),
                      key=lambda r: (ORDER.index(r["model"]), r["epochs_option"] or 0, r.get("variant", ""),
                                     bool(r.get("causal"))))
        out += [f"**{task['title']}** (leave one user out, users "
                f"{', '.join(str(f['user']) for f in rows[0]['folds']) if rows else 'B..I'}; literature, kinematics "
                f"only: accuracy ~{task['literature_accuracy']:.2f}; target at the defaults: accuracy >= "
                f"{task['target_accuracy']:.2f} with edit >= {report['target_edit']:g})", ""]
        if not rows:
            out += ["Not measured yet.", ""]
            continue
        out += ["| model | epochs | folds | acc | edit | F1@10 | F1@25 | F1@50 | video acc | video edit | video F1@10 | "
                "video F1@25 | video F1@50 | acc over folds, mean ± sd | per-fold acc | wall time | target met |",
                "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            p, v, m, s = r["pooled"], r["per_video"], r["fold_mean"], r["fold_sd"]
            sd = "" if s["accuracy"] is None else f" ± {_pct(s['accuracy'])}"
            folds = " ".join(f"{f['user']} {_pct(f['accuracy'])}" for f in r["folds"])
            out.append(f"| {_title(r, rows)} | {r['epochs']} | {len(r['folds'])}/{r['n_folds']} | "
                       f"{_pct(p['accuracy'])} | {p['edit']:.1f} | {p['f1@10']:.1f} | {p['f1@25']:.1f} | "
                       f"{p['f1@50']:.1f} | {_pct(v['accuracy'])} | {v['edit']:.1f} | {v['f1@10']:.1f} | "
                       f"{v['f1@25']:.1f} | {v['f1@50']:.1f} | {_pct(m['accuracy'])}{sd} | {folds} | {_minutes(r)} | "
                       f"{_meets(r, task['target_accuracy'], report['target_edit'])} |")
        out.append("")
    return out


def _not_measured(report: dict[str, Any]) -> list[str]:
    defaults = [r.get("inputs") for r in report["rows"] if not r.get("variant") and r["model"] != "baseline"]
    have = {(r["task"], r["model"]) for r in report["rows"]
            if r["epochs_option"] is None and not r["missing_folds"] and not r.get("causal")
            and (not r.get("variant") or any(_same_inputs(r.get("inputs"), d) for d in defaults))}
    return [f"{report['tasks'][t]['title']} {TITLES[m]}" for t in report["tasks"] for m in ORDER if (t, m) not in have]


def _inputs(report: dict[str, Any]) -> str:
    """The model inputs of the rows (modalities, features, sides, rate), each distinct one once."""
    seen = {json.dumps(r.get("inputs"), sort_keys=True) for r in report["rows"]}
    texts = []
    for text in sorted(seen):
        i = json.loads(text) or {}
        rate = "the aligned rate" if i.get("rate_hz") is None else f"{i['rate_hz']:g} Hz"
        texts.append(f"{'+'.join(i.get('modalities') or [])} {','.join(i.get('features') or [])}, sides "
                     f"{','.join(i.get('sides') or [])}, {rate}")
    return "; ".join(texts) or "none yet"


def gestures_jigsaws_section(report: dict[str, Any]) -> list[str]:
    """The BENCHMARKS.md section: how it was run, the machine, the tables, what is not measured yet."""
    m = report["machine"]
    missing = _not_measured(report)
    out = ["## Gesture recognition on real kinematics (JIGSAWS development tasks) (`gestures_jigsaws.py`)", "",
           "`nice -n 19 .venv/bin/python benchmarks/gestures_jigsaws.py --jobs 2` (`--tasks`, `--models`, "
           "`--epochs` run parts): the JIGSAWS Knot Tying and Needle Passing archives of `../shared/data/jigsaws-dev` "
           "imported (`midas import jigsaws`) and aligned, then `midas train gestures --split louo --fold all` "
           f"per model at its defaults (inputs as the CLI picks them for robot data: {_inputs(report)}). Trials "
           "without a transcription are skipped by the CLI (unlabelled). Last run: "
           f"{m['date_utc']}, {m['cpu_model']}, {m['affinity_cpus']} usable CPUs of {m['cpus']} (shared with "
           f"other engineers' jobs), torch {report['torch']}, nice {report['niceness']}; threads per worker: "
           "cores / --jobs (the local executor's OMP_NUM_THREADS).", "",
           "acc in %, edit and F1@k 0-100. acc, edit, F1@k: *pooled*, every test frame / segment of every fold "
           "counted together (F1@k from TP/FP/FN summed over all test videos, the MS-TCN way); *video* columns: "
           "each test video scored alone, then the mean over videos (cv.json's `per_video`). The literature "
           "figures (jigsaws-dev README) are for orientation: published LOUO frame accuracy from kinematics only; "
           "the targets are issue 27's. A baseline trained inside a neural model's run (the CLI's default) has "
           "its wall time inside that run's; *a fold* is the span of the folds' own training times (one worker "
           "each).", ""]
    out += gestures_jigsaws_table(report)
    out += curves_table(report["rows"])
    out += causal_table(report["rows"])
    if missing:
        out += [f"Not yet measured (at the defaults, all folds): {', '.join(missing)}.", ""]
    return out + [f"* {note}" for note in report.get("notes", [])] + ([""] if report.get("notes") else [])


def curves_table(rows: list[dict[str, Any]]) -> list[str]:
    """The learning curves of runs trained with --curve-every: pooled accuracy / mean edit (raw) by epoch."""
    curved = [r for r in rows if r.get("curve")]
    if not curved:
        return []
    epochs = sorted({e for r in curved for e in r["curve"]["epochs"]})
    out = ["Learning curves (`--train-args \"--curve-every N\"`): the test folds scored while training, raw "
           "predictions (no --min-segment), pooled accuracy % / mean edit over the test videos, at each scored "
           "epoch every fold reached; never used to train or to pick weights.", "",
           "| run | folds | " + " | ".join(f"epoch {e}" for e in epochs) + " |",
           "|---|---|" + "---|" * len(epochs)]
    for r in curved:
        c = r["curve"]
        task_rows = [x for x in rows if x["task"] == r["task"]]
        at = {e: (a, d) for e, a, d in zip(c["epochs"], c["accuracy"], c["edit"])}
        cells = [f"{100 * at[e][0]:.1f} / {at[e][1]:.1f}" if e in at else "" for e in epochs]
        out.append(f"| {r['task']} {_title(r, task_rows)} | {c['folds']} | " + " | ".join(cells) + " |")
    return out + [""]


def rescored_table(rows: list[dict[str, Any]]) -> list[str]:
    """rescore_jigsaws.py's rows: one per (task, run, --min-segment setting)."""
    out = ["| task | run | clean-up | folds | min frames per fold | acc | edit | F1@10 | F1@25 | F1@50 | video acc "
           "| video edit |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        p, v = r["pooled"], r["per_video"]
        runs = " + ".join(run.rstrip("/").rsplit("/", 1)[-1] for run in r["run_dir"].split(" + "))
        out.append(f"| {r['task']} | {runs} | {r['setting']} | {r['folds']} | "
                   f"{' '.join(map(str, r['min_segment_frames']))} | {100 * p['accuracy']:.1f} | {p['edit']:.1f} | "
                   f"{p['f1@10']:.1f} | {p['f1@25']:.1f} | {p['f1@50']:.1f} | {100 * v['accuracy']:.1f} | "
                   f"{v['edit']:.1f} |")
    return out


def rescored_section(report: dict[str, Any]) -> list[str]:
    """The clean-up's effect (``--min-segment``) on the development runs' raw predictions."""
    return ["### The offline clean-up on the development tasks (`rescore_jigsaws.py`)", "",
            f"Rendered from `results/gestures_jigsaws_rescored.json` ({report['machine']['date_utc'][:10]}): the raw "
            "predictions of the runs above (from their checkpoints) re-scored with `--min-segment` settings (no "
            "training again; each fold's minimum from its own training split, as `train gestures` computes it; `pN` = "
            "the N-th percentile of the training gestures' lengths, `auto` the default's: the 5th until 2026-11-27, "
            "the 2nd since, chosen here); `A + B`: the ensemble of those runs, their frame probabilities averaged "
            "per fold (what `--model ensemble` does with its members). A bare setting is the greedy merge "
            "(`--grammar none`); `gW-S` decodes with the training gesture order at weight W and minimum S "
            "(`--grammar W --min-segment S`; `g10-auto` is the default at 10 Hz since 2026-11-27), `gW+S` decodes with "
            "no minimum and merges at S after, `sP-S` decodes with any order equally likely, each change costing P "
            "nats, `v-S` with no order at all; `oL-` before a decoding (`o5-g10-auto`): decoded as a live decoder "
            "lagging L frames would (`postprocess.decode_online`: each frame labelled L frames later from the best "
            "path so far), for causal runs (their own clean-up until 2026-11-27 was none; since, it is this with L = "
            "`--decode-lag`, default 0). acc in %.", "",
            *rescored_table(report["rows"]), ""]
