"""PNG figures like the paper's: trajectory overlays per axis, pedal step plots with the overlap
shaded, grasper open/closed states. Drawn with matplotlib (Agg backend, no display needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from midas_cli.analysis.evaluation import AXES
from midas_cli.errors import ConfigError
from midas_cli.geometry import unwrap_deg
from midas_cli.session.derived import AlignedTable
from midas_cli.session.outputs import out_target, replacing


def pyplot(what: str = "plots", otherwise: str = " (or run with --no-plots)"):
    """matplotlib's pyplot on the Agg backend (files, no display); ConfigError if it is not installed."""
    try:
        import matplotlib
    except ImportError as exc:
        raise ConfigError(f"{what} need matplotlib: pip install matplotlib{otherwise}") from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def draw_markers(axes: list, t_s, texts: list[str]) -> None:
    """Markers (the events stream) as dotted purple lines on every axis, their text on the first."""
    for ax in axes:
        for x in t_s:
            ax.axvline(x, color="tab:purple", lw=0.8, ls=":", zorder=0)
    for x, text in zip(t_s, texts):
        label = text if len(text) <= 28 else text[:27] + "…"
        axes[0].annotate(label, (x, 0.98), xycoords=("data", "axes fraction"), rotation=90, fontsize=7,
                         va="top", ha="right", color="tab:purple")


def trajectory_figure(table: AlignedTable, hand: str, sources: dict[str, str], path: Path, title: str) -> Path | None:
    """Six rows (X, Y, Z, roll, pitch, yaw) by two columns: MTM (left) and PSM (right), each with the
    source calibrated onto it (``sources``: target "mtm"/"psm" -> column prefix, e.g. ``emht_mtm_rigid``)
    dashed over it. Angles are unwrapped (no vertical lines where yaw crosses +-180 deg); a source's
    angle is shifted by whole turns to lie within half a turn of its target's."""
    plt = pyplot()
    t = table.times_s()
    fig, axes = plt.subplots(6, 2, figsize=(13, 11), sharex=True)
    drawn = False
    for col, target in enumerate(("mtm", "psm")):
        for row, (axis, suffix) in enumerate(AXES):
            ax = axes[row, col]
            reference = None
            for column, label, style in ((f"{target}.{hand}_{suffix}", target.upper(), "-"),
                                         (f"{sources.get(target)}.{hand}_{suffix}", sources.get(target), "--")):
                if label is None or not table.has(column):
                    continue
                values = np.asarray(table.column(column), dtype=float)
                if suffix.endswith("deg"):
                    values = unwrap_deg(values, reference)
                    reference = values if reference is None else reference
                ax.plot(t, values, style, lw=1, label=label)
                drawn = True
            ax.set_ylabel(f"{axis} ({'mm' if suffix.endswith('mm') else 'deg, unwrapped'})", fontsize=8)
        axes[0, col].set_title(f"{target.upper()} ({hand} hand)")
        axes[0, col].legend(loc="upper right", fontsize=8)
        axes[-1, col].set_xlabel("time since first frame (s)")
    if not drawn:
        plt.close(fig)
        return None
    fig.suptitle(title)
    return _save(plt, fig, path)


def pedal_figure(t_s: np.ndarray, truth: np.ndarray, detected: np.ndarray, path: Path, title: str) -> Path:
    """Step plot of ground truth and detection with frames where both are pressed shaded."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(10, 2.6))
    ax.step(t_s, truth + 0.02, where="post", lw=1.2, label="ground truth")
    ax.step(t_s, detected - 0.02, where="post", lw=1.2, label="FPS detection")
    both = (truth > 0.5) & (detected > 0.5)
    ax.fill_between(t_s, 0, 1, where=both, step="post", alpha=0.25, color="tab:green", label="overlap (IoU)")
    ax.set_yticks([0, 1], ["released", "pressed"])
    ax.set_xlabel("time since first frame (s)")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8)
    return _save(plt, fig, path)


def grasper_figure(t_s: np.ndarray, states: dict[str, np.ndarray], path: Path, title: str) -> Path:
    """Closed (1) / open (0) step plots of each source, offset vertically."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(10, 3))
    for k, (label, values) in enumerate(states.items()):
        ax.step(t_s, values + 1.5 * k, where="post", lw=1, label=label)
    ax.set_yticks([1.5 * k + 0.5 for k in range(len(states))], list(states))
    ax.set_xlabel("time since first frame (s)")
    ax.set_title(title + " (high = closed)")
    return _save(plt, fig, path)


def _save(plt, fig, path: Path) -> Path:
    fig.tight_layout()
    try:
        with replacing(out_target(path)) as tmp:
            fig.savefig(tmp, dpi=110, format=Path(path).suffix.lstrip(".") or "png")
    finally:
        plt.close(fig)
    return path


def sync_figure(pairs: list[tuple[str, list[tuple[float, float]], float]], threshold_ms: float, path: Path,
                title: str) -> Path:
    """Offset (ms) of each modality pair over the session: one marker per window or matched event, the
    pair's overall offset as a line, the threshold as a band."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(10, 3.2))
    ax.axhspan(-threshold_ms, threshold_ms, color="tab:green", alpha=0.12, label=f"within ±{threshold_ms:g} ms")
    for k, (name, points, offset) in enumerate(pairs):
        colour = f"C{k}"
        if points:
            t, ms = zip(*points)
            ax.plot(t, ms, "o", ms=4, color=colour, label=name)
        ax.axhline(offset, color=colour, lw=1, ls="--")
    ax.set_xlabel("time since session start (s)")
    ax.set_ylabel("offset (ms, + = second is late)")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8)
    return _save(plt, fig, path)
