"""Writing evaluation tables as CSV, JSON, Markdown and LaTeX (booktabs), labelled with their data source."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pandas as pd

from midas_cli.session.outputs import out_folder, out_target, replacing, write_text


def format_cell(value: Any, digits: int = 3) -> str:
    """Numbers rounded to ``digits`` (NaN -> "--"), everything else as text."""
    if isinstance(value, float):
        return "--" if math.isnan(value) else f"{value:.{digits}f}"
    return str(value)


def to_markdown(frame: pd.DataFrame, digits: int = 3) -> str:
    """A GitHub-flavoured Markdown table."""
    header = "| " + " | ".join(map(str, frame.columns)) + " |"
    rule = "|" + "|".join("---" for _ in frame.columns) + "|"
    body = ["| " + " | ".join(format_cell(v, digits) for v in row) + " |" for row in frame.itertuples(index=False)]
    return "\n".join([header, rule, *body]) + "\n"


def to_latex(frame: pd.DataFrame, caption: str, label: str, digits: int = 3) -> str:
    """A booktabs LaTeX table (``\\usepackage{booktabs}``)."""
    escape = lambda text: str(text).replace("_", r"\_").replace("%", r"\%").replace("&", r"\&")  # noqa: E731
    align = "l" + "c" * (len(frame.columns) - 1)
    lines = [r"\begin{table}[t]", r"\centering", rf"\caption{{{escape(caption)}}}", rf"\label{{{label}}}",
             rf"\begin{{tabular}}{{@{{}}{align}@{{}}}}", r"\toprule",
             " & ".join(escape(c) for c in frame.columns) + r" \\", r"\midrule"]
    lines += [" & ".join(escape(format_cell(v, digits)) for v in row) + r" \\" for row in frame.itertuples(index=False)]
    lines += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(lines) + "\n"


def write_tables(out_dir: Path, name: str, tables: dict[str, tuple[pd.DataFrame, str]], rows: dict[str, list],
                 provenance: dict[str, Any]) -> list[Path]:
    """Write ``tables`` (key -> (table, caption)) as ``<key>.csv``/``<key>.tex``, all of them in
    ``<name>.md``, and ``<name>.json`` with the tables, the per-session ``rows`` and ``provenance``."""
    out_dir = out_folder(out_dir)
    written = []
    label = provenance.get("data_label", "")
    markdown = [f"# {name}\n", f"Data: {label}\n" if label else ""]
    for key, (table, caption) in tables.items():
        csv_path, tex_path = out_dir / f"{key}.csv", out_dir / f"{key}.tex"
        with replacing(out_target(csv_path)) as tmp:
            table.to_csv(tmp, index=False)
        write_text(out_target(tex_path), to_latex(table, f"{caption} ({label})" if label else caption, f"tab:{key}"))
        markdown += [f"## {caption}\n", to_markdown(table), ""]
        written += [csv_path, tex_path]
    for key, records in rows.items():
        path = out_dir / f"{key}_per_session.csv"
        with replacing(out_target(path)) as tmp:
            pd.DataFrame(records).to_csv(tmp, index=False)
        written.append(path)
    md_path, json_path = out_dir / f"{name}.md", out_dir / f"{name}.json"
    write_text(out_target(md_path), "\n".join(markdown))
    document = {"provenance": provenance, "tables": {k: t.to_dict("records") for k, (t, _) in tables.items()},
                "rows": rows}
    write_text(out_target(json_path), json.dumps(json_safe(document), indent=2) + "\n")
    return [*written, md_path, json_path]


def json_safe(value: Any) -> Any:
    """Nested data with numpy scalars as Python numbers and NaN/inf as null (strict JSON)."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if hasattr(value, "item"):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
