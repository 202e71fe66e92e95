"""Ablation runner: model x modality x feature set -> Acc, F1, Prec, Rec, in the layout of the paper's
gesture tables (Appendix B, "Peg Transfer gesture recognition ablation using different modalities").

A grid row is written ``MODALITIES:FEATURES[:exclude-clutch]``: modalities joined with ``+``
(``emht+image``), feature sets with ``,`` (``pos,ori,vel``); ``exclude-clutch`` drops clutch windows
(the paper's default; its "-NC" rows keep them). Every (model, row) is one training run in
``OUT/runs/<model>__<row slug>/``, a unit of a batch run (``ablation_units.py``: here or on SLURM); a
run folder that already holds ``metrics.json`` of the same configuration is reused, so an interrupted
ablation resumes. Rows whose data are missing (no MTM on a da Vinci, no image features)
are listed as skipped with the reason. Scores are fractions of the test split (macro F1, precision,
recall), as in the paper.

Every table has a baseline row per grid row: the per-frame logistic regression (models/baseline.py) on
the same features, so each model is measured against something simple (``baseline=False`` leaves it
out). With ``cv=True`` (a group split, ``--fold all``) every (model, row) is a whole cross-validation
(models/cv.py) in ``OUT/runs/<model>__<row slug>/``; the cells are mean ± sd over folds and the table
gains the segmental columns Edit, F1@10, F1@25, F1@50 (mean ± sd; 0-100).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

from midas_cli.errors import ConfigError, MidasError
from midas_cli.models.data import DatasetConfig
from midas_cli.models.splits import GROUP_SPLITS
from midas_cli.models.registry import MODELS
from midas_cli.models.train import TrainConfig, train_run
from midas_cli.session.outputs import out_target, write_text

log = logging.getLogger(__name__)

MODALITY_TITLES = {"emht": "EmHT", "handkp": "HandKP", "mtm": "MTM", "psm": "PSM", "image": "Image"}
FEATURE_TITLES = {"pos": "pos.", "ori": "ori.", "vel": "vel.", "grasper": "grasp.", "clutch": "clutch"}
PAPER_GRID = (
    "psm:pos,ori,grasper:exclude-clutch", "psm:pos,ori:exclude-clutch", "psm:pos,ori,vel,grasper:exclude-clutch",
    "mtm:pos,ori,grasper:exclude-clutch", "mtm:pos,ori:exclude-clutch", "mtm:pos,ori,vel,grasper:exclude-clutch",
    "emht:pos:exclude-clutch", "emht:pos,ori:exclude-clutch", "emht:pos,vel:exclude-clutch",
    "emht:pos,ori,vel:exclude-clutch", "emht:pos,ori,vel",
    "image:pos:exclude-clutch", "handkp:pos,vel:exclude-clutch", "handkp+image:pos,vel:exclude-clutch",
)
COLUMNS = ("Dataset", "Model", "Modality", "Features", "Acc", "F1", "Prec.", "Rec.")
SCORES = ("accuracy", "f1", "precision", "recall")
CV_COLUMNS = COLUMNS + ("Edit", "F1@10", "F1@25", "F1@50")
CV_SCORES = SCORES + ("edit", "f1@10", "f1@25", "f1@50")


@dataclass(frozen=True)
class GridRow:
    modalities: tuple[str, ...]
    features: tuple[str, ...]
    exclude_clutch: bool

    @classmethod
    def parse(cls, text: str) -> "GridRow":
        parts = text.strip().split(":")
        if len(parts) not in (2, 3) or (len(parts) == 3 and parts[2] != "exclude-clutch"):
            raise ConfigError(f"grid row {text!r} must be MODALITIES:FEATURES[:exclude-clutch], "
                              "e.g. emht+image:pos,ori,vel:exclude-clutch")
        row = cls(tuple(parts[0].split("+")), tuple(parts[1].split(",")), len(parts) == 3)
        DatasetConfig(row.modalities, row.features)  # validates names
        return row

    def slug(self) -> str:
        text = f"{'+'.join(self.modalities)}__{'-'.join(self.features)}{'__xc' if self.exclude_clutch else ''}"
        return re.sub(r"[^A-Za-z0-9_+-]", "_", text)

    def modality_title(self) -> str:
        kinematic = [m for m in self.modalities if m != "image"]
        title = ", ".join(MODALITY_TITLES[m] for m in self.modalities)
        if kinematic and all(m in ("mtm", "psm") for m in kinematic) and "grasper" not in self.features:
            title += "-NG"
        if kinematic and not self.exclude_clutch and "clutch" not in self.features:
            title += "-NC"
        return title

    def feature_title(self) -> str:
        kinematic = any(m != "image" for m in self.modalities)
        names = [FEATURE_TITLES[f] for f in self.features] if kinematic else []
        return ", ".join(names + (["RGB"] if "image" in self.modalities else []))


def check_ablation(models: Sequence[str], base: TrainConfig, cv: bool, baseline: bool) -> list[str]:
    """The models to train (the baseline added unless ``baseline`` is False); ConfigError on a bad choice."""
    unknown = [m for m in models if m not in MODELS]
    if unknown or not models:
        raise ConfigError(f"--models {','.join(unknown or models)!r}: expected a comma list of {', '.join(MODELS)}")
    if cv and base.split not in GROUP_SPLITS:
        raise ConfigError(f"--fold all needs a group split ({', '.join(GROUP_SPLITS)}), not --split {base.split}")
    return list(models) + (["baseline"] if baseline and "baseline" not in models else [])


def run_cell(sessions: Sequence[Path], model: str, row: GridRow, base: TrainConfig, out_dir: Path,
             progress: Callable[[int, int, dict], None] | None = None, cv: bool = False) -> dict:
    """One (model, row) cell: its table row, or ``{"skipped": ...}`` when its data are missing."""
    try:
        summary, title = _run_one(sessions, model, row, base, Path(out_dir) / "runs" / f"{model}__{row.slug()}",
                                  progress, cv)
    except MidasError as exc:
        log.warning("ablation row %s / %s skipped: %s", model, row.slug(), exc)
        return {"skipped": {"model": model, "row": row.slug(), "reason": str(exc), "exit_code": exc.exit_code}}
    return {"dataset": title, "model": MODELS[model].title, "modality": row.modality_title(),
            "features": row.feature_title(), **summary}


def finish_ablation(out_dir: Path, cells: Sequence[dict], base: TrainConfig, cv: bool) -> dict:
    """Write ``table.{md,tex,csv}`` and ``ablation.json`` from the cells (in table order). When no cell ran,
    the error has the first skipped cell's exit code (damaged data: 4, as when a command reads it)."""
    results = [c for c in cells if "skipped" not in c]
    skipped = [c["skipped"] for c in cells if "skipped" in c]
    if not results:
        error = ConfigError(f"no ablation row could run ({len(skipped)} skipped; first reason: "
                            f"{skipped[0]['reason'] if skipped else 'empty grid'})")
        code = skipped[0].get("exit_code") if skipped else None
        if type(code) is int and code in (3, 4):  # a unit's result is a file: only a known code is taken
            error.exit_code = code
        raise error
    report = {"results": results, "skipped": skipped, "train_config": {**base.__dict__}, "cross_validation": cv}
    write_tables(out_dir, results, skipped)
    write_text(out_target(Path(out_dir) / "ablation.json"), json.dumps(report, indent=2) + "\n")
    return report


def _run_one(sessions: Sequence[Path], model: str, row: GridRow, base: TrainConfig, run_dir: Path,
             progress, cv: bool = False) -> tuple[dict, str]:
    """The row's scores (``cv``: mean, ``<key>_sd`` and the fold count) and the dataset title."""
    data = DatasetConfig(row.modalities, row.features, exclude_clutch=row.exclude_clutch)
    if cv:
        from midas_cli.models.cv import fold_dir, run_cv, summarise

        report = run_cv(sessions, data, replace(base, model=model), run_dir, baseline=None, progress=progress,
                        batched=base.device == "cuda") \
            or summarise(run_dir)
        run = json.loads((fold_dir(run_dir, report["folds"][0]["fold"]) / "run.json").read_text(encoding="utf-8"))
        scores = {k: report["mean"][k] for k in CV_SCORES}
        scores.update({f"{k}_sd": report["sd"][k] for k in CV_SCORES})
        return {**scores, "folds": len(report["folds"]), "validation": report["validation"]}, dataset_title(run["trials"])
    metrics_path, run_path = run_dir / "metrics.json", run_dir / "run.json"
    if not metrics_path.is_file():
        train_run(sessions, data, replace(base, model=model), run_dir, progress)
    run = json.loads(run_path.read_text(encoding="utf-8"))
    summary = json.loads(metrics_path.read_text(encoding="utf-8"))["test"]["summary"]
    return {k: summary[k] for k in SCORES}, dataset_title(run["trials"])


def dataset_title(trials: list[dict]) -> str:
    platforms = sorted({t["platform"] for t in trials})
    names = {"raven-ii": "Raven-II", "davinci-xi": "da Vinci Xi"}
    return f"{' / '.join(names.get(p, p) for p in platforms)} ({len(trials)} trials)"


def _score(result: dict, key: str) -> str:
    """Fractions with 2 decimals, edit/F1@k (0-100) with 1; ``± sd`` over folds when cross-validated."""
    digits = 1 if key == "edit" or key.startswith("f1@") else 2
    sd = result.get(f"{key}_sd")
    return f"{result[key]:.{digits}f}" + (f" ± {sd:.{digits}f}" if sd is not None else "")


def write_tables(out_dir: Path, results: list[dict], skipped: list[dict]) -> dict[str, Path]:
    cv = any("folds" in r for r in results)
    columns, scores = (CV_COLUMNS, CV_SCORES) if cv else (COLUMNS, SCORES)
    rows = [[r["dataset"], r["model"], r["modality"], r["features"], *(_score(r, k) for k in scores)]
            for r in results]
    paths = {"md": out_dir / "table.md", "tex": out_dir / "table.tex", "csv": out_dir / "table.csv"}
    write_text(out_target(paths["md"]), markdown_table(rows, skipped, columns))
    write_text(out_target(paths["tex"]), latex_table(rows, columns))
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    writer.writerows(rows)
    write_text(out_target(paths["csv"]), buffer.getvalue())
    return paths


def markdown_table(rows: list[list[str]], skipped: list[dict], columns: Sequence[str] = COLUMNS) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * 4 + "---:|" * (len(columns) - 4)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    if skipped:
        lines += ["", "Skipped: " + "; ".join(f"{s['model']} {s['row']} ({s['reason']})" for s in skipped)]
    return "\n".join(lines) + "\n"


def latex_table(rows: list[list[str]], columns: Sequence[str] = COLUMNS) -> str:
    """A booktabs tabular with the paper's columns; a rule between models."""
    out = [f"\\begin{{tabular}}{{@{{}}llll{'c' * (len(columns) - 4)}@{{}}}}", "\\toprule",
           " & ".join(f"\\textbf{{{c}}}" for c in columns) + " \\\\", "\\midrule"]
    previous = None
    for row in rows:
        if previous is not None and row[1] != previous:
            out.append(f"\\cmidrule(l){{2-{len(columns)}}}")
        previous = row[1]
        out.append(" & ".join(_latex_escape(c) for c in row) + " \\\\")
    out += ["\\bottomrule", "\\end{tabular}"]
    return "\n".join(out) + "\n"


def _latex_escape(text: str) -> str:
    return (text.replace("\\", "\\textbackslash{}").replace("&", "\\&").replace("%", "\\%").replace("_", "\\_")
            .replace("±", "$\\pm$"))


def parse_grid(text: str | None) -> list[GridRow]:
    """Rows from ``;``-separated specs, or the paper's Raven-II grid when ``text`` is empty."""
    specs = [s for s in (text.split(";") if text else PAPER_GRID) if s.strip()]
    return [GridRow.parse(s) for s in specs]

