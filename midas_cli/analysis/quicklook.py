"""One quick-look page of a session (``midas plot``): every stream against session time on one PNG.

Panels, top to bottom: each stream's rate per second against its nominal rate; then one panel per
stream (EmHT positions per sensor, the pedal board's pressed states, HandKP thumb-middle distance with
its detection gaps, video frame intervals, the first columns of any other stream); then the gesture
label ribbon (``labels/gestures.csv``) when the session has one. Sequence gaps the manifest lists and
device outages (its devices' ``lost`` -> ``opened`` events) are shaded on every panel of their stream
and on the rate panel. Long streams are thinned for drawing (the page shows shape, not every sample).
Drawn with matplotlib (Agg backend; no display needed).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.analysis.figures import draw_markers, pyplot
from midas_cli.session.labels import label_set_files, list_label_sets, read_frame_labels
from midas_cli.session.outputs import out_target, replacing, session_target
from midas_cli.session.reader import Session

DEFAULT_OUT = "derived/plots/quicklook.png"
MAX_POINTS = 3000  # per line drawn: longer streams are thinned (every k-th sample)
GAP_FACTOR = 3.0  # an interval over this many nominal periods breaks a line instead of bridging it
SEQ_GAP_COLOUR, OUTAGE_COLOUR, UNLABELLED_COLOUR = "tab:red", "tab:orange", "0.75"
SENSOR_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink")
AXIS_STYLES = {"x": "-", "y": "--", "z": ":"}


@dataclass
class Gap:
    """A shaded interval of one stream, in seconds since the session start."""

    stream: str
    kind: str  # "seq_gap" (samples missing between two rows) or "outage" (device lost -> reopened)
    start_s: float
    end_s: float
    missing: int | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"stream": self.stream, "kind": self.kind, "start_s": round(self.start_s, 3),
                "end_s": round(self.end_s, 3), "missing": self.missing}


@dataclass
class QuickLook:
    """What was drawn: the page's file, title, panels (name, stream, what they show) and gaps shaded."""

    out: Path
    title: str
    panels: list[dict[str, Any]] = field(default_factory=list)
    gaps: list[Gap] = field(default_factory=list)
    rates: dict[str, dict[str, Any]] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {"out": str(self.out), "title": self.title, "panels": self.panels,
                "gaps": [g.as_dict() for g in self.gaps], "rates": self.rates}


def _pyplot():
    return pyplot("midas plot and its figures", "")


def default_out(session_path: Path | str) -> Path:
    """Where the page goes without --out: ``SESSION/derived/plots/quicklook.png`` (checked, folder made)."""
    return session_target(session_path, DEFAULT_OUT)


def quicklook(session_path: Path | str, out: Path | str | None = None, dpi: int = 80) -> QuickLook:
    """Draw the quick-look page of ``session_path`` to ``out`` (default ``derived/plots/quicklook.png``)."""
    session = Session.open(session_path)
    start_ns = int(session.manifest["start"]["host_ns"])
    title = Path(session_path).resolve().name
    target = default_out(session_path) if out is None else out_target(out, inputs=label_set_files(session.path, "gestures"))
    streams = {name: _read(session, name, start_ns) for name in session.stream_names}
    events = streams.pop("events", None)  # markers: dotted lines on every panel, not a panel of their own
    gaps = [g for name in streams for g in _seq_gaps(session, name, streams[name])] + _outages(session, start_ns)
    labels = _labels(session, streams.get("video"))

    plt = _pyplot()
    n_panels = 1 + len(streams) + (labels is not None)
    heights = [1.6] + [2.0] * len(streams) + ([0.9] if labels is not None else [])
    fig, axes = plt.subplots(n_panels, 1, figsize=(12, sum(heights) + 1.2), sharex=True,
                             gridspec_kw={"height_ratios": heights}, squeeze=False)
    axes = list(axes[:, 0])
    result = QuickLook(Path(target), title)
    result.rates = _rate_panel(axes[0], session, streams)
    result.panels.append({"name": "rates", "stream": None, "shows": "samples per second / nominal rate"})
    for gap in gaps:
        _shade(axes[0], gap)
    for ax, (name, data) in zip(axes[1:], streams.items()):
        shows = _stream_panel(ax, session, name, data)
        result.panels.append({"name": name, "stream": name, "shows": shows})
        for gap in gaps:
            if gap.stream in (name, session.manifest["streams"][name].get("device")):
                _shade(ax, gap)
    if labels is not None:
        _label_panel(axes[-1], *labels)
        result.panels.append({"name": "labels", "stream": None, "shows": "labels/gestures.csv on the video clock"})
    result.gaps = gaps
    if events is not None and len(events.t):
        draw_markers(axes, events.t, ["" if t is None else str(t) for t in events.table["text"]])
        result.panels.append({"name": "markers", "stream": "events", "shows": f"{len(events.t)} marker(s), dotted"})
    _legend_for_gaps(axes[0], gaps)
    axes[-1].set_xlabel("session time (s since the session start)")
    end_s = _end_s(session, streams)
    if end_s > 0:
        axes[-1].set_xlim(0, end_s)
    meta = session.metadata
    subtitle = (f"task {meta.get('task', '?')}, subject {meta.get('subject', '?')}, trial {meta.get('trial', '?')}"
                f"  |  status {session.status}  |  {end_s:.1f} s  |  {len(gaps)} gap(s)/outage(s) shaded")
    fig.suptitle(f"{title}\n{subtitle}", fontsize=11)
    fig.tight_layout()
    try:
        with replacing(target) as tmp:
            fig.savefig(tmp, dpi=dpi, format="png")
    finally:
        plt.close(fig)
    return result


# ---- data ----------------------------------------------------------------------------------------

@dataclass
class _Stream:
    t: np.ndarray  # seconds since the session start, per row
    seq: np.ndarray
    table: np.ndarray  # the structured array (one field per column)
    nominal_hz: float | None


def _read(session: Session, name: str, start_ns: int) -> _Stream:
    table = session.read_columns(name, allow_incomplete=True)
    t = (np.asarray(table["t_host_ns"], dtype=np.int64) - start_ns) / 1e9 if len(table) else np.zeros(0)
    nominal = session.manifest["streams"][name].get("nominal_rate_hz")
    return _Stream(t, np.asarray(table["seq"], dtype=np.int64), table, float(nominal) if nominal else None)


def _seq_gaps(session: Session, name: str, data: _Stream) -> list[Gap]:
    """The manifest's listed sequence gaps, from the last row before to the first row after each."""
    listed = ((session.manifest["streams"][name].get("seq_gaps") or {}).get("listed")) or []
    gaps = []
    for entry in listed:
        after, nxt = entry.get("after_seq"), entry.get("next_seq")
        if after is None or nxt is None or not len(data.seq):
            continue
        i = np.searchsorted(data.seq, after, side="right") - 1
        j = np.searchsorted(data.seq, nxt, side="left")
        if 0 <= i < len(data.t) and j < len(data.t):
            gaps.append(Gap(name, "seq_gap", float(data.t[i]), float(data.t[j]), int(nxt) - int(after) - 1))
    return gaps


def _outages(session: Session, start_ns: int) -> list[Gap]:
    """Each device's outages from its manifest events: ``lost`` until the next ``opened`` (or the end)."""
    stop_ns = (session.manifest.get("stop") or {}).get("host_ns")
    gaps = []
    for device, entry in (session.manifest.get("devices") or {}).items():
        lost_at = None
        for event in entry.get("events") or []:
            kind, t_ns = event.get("event"), event.get("t_host_ns")
            if t_ns is None:
                continue
            if kind == "lost" and lost_at is None:
                lost_at = t_ns
            elif kind == "opened" and lost_at is not None:
                gaps.append(Gap(device, "outage", (lost_at - start_ns) / 1e9, (t_ns - start_ns) / 1e9))
                lost_at = None
        if lost_at is not None and stop_ns is not None:
            gaps.append(Gap(device, "outage", (lost_at - start_ns) / 1e9, (stop_ns - start_ns) / 1e9))
    return gaps


def _labels(session: Session, video: _Stream | None) -> tuple[np.ndarray, np.ndarray, list[str]] | None:
    """(start_s, end_s, label) per frame of labels/gestures.csv on the video clock; None without either."""
    if video is None or "gestures" not in list_label_sets(session.path) or not len(video.t):
        return None
    labels = read_frame_labels(session.path, "gestures")
    index = np.searchsorted(video.seq, labels.frames)
    ok = (index < len(video.seq)) & (video.seq[np.minimum(index, len(video.seq) - 1)] == labels.frames)
    start = video.t[index[ok]]
    period = 1.0 / video.nominal_hz if video.nominal_hz else float(np.median(np.diff(video.t))) if len(video.t) > 1 else 0.03
    return start, start + period, [str(x) for x in labels.labels[ok]]


def _end_s(session: Session, streams: dict[str, _Stream]) -> float:
    duration = session.duration_s()
    if duration is not None:
        return float(duration)
    return max((float(s.t[-1]) for s in streams.values() if len(s.t)), default=0.0)


def _thin(n: int) -> slice:
    return slice(None, None, max(1, n // MAX_POINTS))


def _with_breaks(t: np.ndarray, y: np.ndarray, nominal_hz: float | None) -> tuple[np.ndarray, np.ndarray]:
    """``t, y`` with NaN inserted where consecutive samples are far apart (lines break at gaps)."""
    if len(t) < 2:
        return t, y
    limit = GAP_FACTOR / nominal_hz if nominal_hz else 10 * float(np.median(np.diff(t)) or 1.0)
    breaks = np.flatnonzero(np.diff(t) > limit) + 1
    return np.insert(t, breaks, np.nan), np.insert(y.astype(float), breaks, np.nan)


def _line(ax, data: _Stream, values: np.ndarray, **style) -> None:
    keep = _thin(len(values))
    t, y = _with_breaks(data.t[keep], np.asarray(values, dtype=float)[keep],
                        data.nominal_hz / max(1, keep.step or 1) if data.nominal_hz else None)
    ax.plot(t, y, lw=0.8, **style)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) index runs where ``mask`` is true."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


def _bars(ax, t: np.ndarray, mask: np.ndarray, y: float, height: float, period: float, **style) -> None:
    """Horizontal bars where ``mask`` holds (run-length encoded: exact however long the stream)."""
    spans = [(float(t[a]), float(t[b - 1]) - float(t[a]) + period) for a, b in _runs(mask)]
    if spans:
        ax.broken_barh(spans, (y - height / 2, height), **style)


# ---- panels --------------------------------------------------------------------------------------

def _rate_panel(ax, session: Session, streams: dict[str, _Stream]) -> dict[str, dict[str, Any]]:
    """Samples per 1-s bin / nominal rate (in %), one line per stream; event streams as counts."""
    rates = {}
    for name, data in streams.items():
        entry = session.manifest["streams"][name]
        rates[name] = {"nominal_hz": data.nominal_hz, "measured_hz": entry.get("measured_rate_hz"),
                       "samples": int(len(data.t))}
        if not len(data.t):
            continue
        first, last = float(data.t[0]), float(data.t[-1])
        edges = np.append(np.arange(first, last, 1.0), last)  # 1-s bins from the first sample, last one short
        if len(edges) < 2 or not data.nominal_hz:
            continue
        counts, _ = np.histogram(data.t, edges)
        widths = np.diff(edges)
        full = widths >= 0.5  # a last bin under half a second says little about the rate
        per_s = counts[full] / widths[full]
        if len(per_s):
            ax.step(np.append(edges[:-1][full], edges[1:][full][-1]), 100.0 * np.append(per_s, per_s[-1]) / data.nominal_hz,
                    where="post", lw=1,
                    label=f"{name} ({entry.get('measured_rate_hz', '?')} / {data.nominal_hz:g} Hz)")
    ax.axhline(100, color="0.4", lw=0.6, ls="--")
    ax.set_ylabel("rate\n(% of nominal)")
    ax.set_ylim(0, 130)
    ax.legend(loc="lower left", fontsize=7, ncol=min(4, max(1, len(streams))))
    ax.set_title("rate per second (measured / nominal Hz in the legend)", fontsize=9, loc="left")
    return rates


def _stream_panel(ax, session: Session, name: str, data: _Stream) -> str:
    columns = [c for c in data.table.dtype.names or () if c not in ("seq", "t_host_ns")]
    kind = session.manifest["streams"][name].get("device")
    kind = (session.manifest.get("devices") or {}).get(kind, {}).get("kind", "")
    if not len(data.t):
        ax.text(0.5, 0.5, f"{name}: no samples", transform=ax.transAxes, ha="center", va="center")
        ax.set_ylabel(name)
        return "no samples"
    if any(re.fullmatch(r"s\d+_x_mm", c) for c in columns):
        return _emht_panel(ax, name, data, columns)
    if any(c.endswith("_pressed") for c in columns):
        return _pedal_panel(ax, name, data, columns)
    if any(c.endswith("_detected") for c in columns):
        return _handkp_panel(ax, name, data, columns)
    if kind == "video" or columns in (["t_device_s"], ["t_device_s", "segment"]):
        return _interval_panel(ax, name, data)
    return _generic_panel(ax, name, data, columns)


def _emht_panel(ax, name: str, data: _Stream, columns: list[str]) -> str:
    sensors = sorted({int(m.group(1)) for c in columns if (m := re.fullmatch(r"s(\d+)_x_mm", c))})
    for k, sensor in enumerate(sensors):
        colour = SENSOR_COLOURS[k % len(SENSOR_COLOURS)]
        for axis, style in AXIS_STYLES.items():
            values = np.asarray(data.table[f"s{sensor}_{axis}_mm"], dtype=float)
            centre = np.nanmedian(values) if np.isfinite(values).any() else 0.0
            _line(ax, data, values - centre, color=colour, ls=style,
                  label=f"s{sensor}" if axis == "x" else None)
    ax.set_ylabel(f"{name}\nposition - median (mm)")
    ax.legend(loc="upper right", fontsize=7, ncol=len(sensors), title="sensor (x solid, y dashed, z dotted)",
              title_fontsize=7)
    ax.set_title(f"{name}: EmHT positions", fontsize=9, loc="left")
    return "EmHT positions"


def _pedal_panel(ax, name: str, data: _Stream, columns: list[str]) -> str:
    channels = [c for c in columns if c.endswith("_pressed")]
    period = 1.0 / data.nominal_hz if data.nominal_hz else 0.0
    for k, column in enumerate(channels):
        pressed = np.nan_to_num(np.asarray(data.table[column], dtype=float)) > 0.5
        _bars(ax, data.t, pressed, k, 0.7, period, color="tab:blue")
    ax.set_yticks(range(len(channels)), [c.removesuffix("_pressed") for c in channels], fontsize=7)
    ax.set_ylim(-0.6, len(channels) - 0.4)
    ax.set_ylabel(f"{name}\npressed")
    ax.set_title(f"{name}: pedal states (bar = pressed)", fontsize=9, loc="left")
    return "pedal states"


def _handkp_panel(ax, name: str, data: _Stream, columns: list[str]) -> str:
    hands = [c.removesuffix("_detected") for c in columns if c.endswith("_detected")]
    period = 1.0 / data.nominal_hz if data.nominal_hz else 0.0
    for k, hand in enumerate(hands):
        colour = SENSOR_COLOURS[k % len(SENSOR_COLOURS)]
        if all(f"{hand}_{f}_{a}_mm" in columns for f in ("thumb", "middle") for a in "xyz"):
            thumb = np.stack([data.table[f"{hand}_thumb_{a}_mm"] for a in "xyz"], axis=1).astype(float)
            middle = np.stack([data.table[f"{hand}_middle_{a}_mm"] for a in "xyz"], axis=1).astype(float)
            _line(ax, data, np.linalg.norm(thumb - middle, axis=1), color=colour, label=f"{hand} thumb-middle")
        missing = np.nan_to_num(np.asarray(data.table[f"{hand}_detected"], dtype=float)) < 0.5
        _bars(ax, data.t, missing, -8 - 10 * k, 8, period, color=colour, alpha=0.8)
    ax.set_ylabel(f"{name}\ndistance (mm)")
    ax.legend(loc="upper right", fontsize=7, ncol=len(hands))
    ax.set_title(f"{name}: hand keypoints (bars below 0 = hand not detected)", fontsize=9, loc="left")
    return "HandKP thumb-middle distance and detection gaps"


def _interval_panel(ax, name: str, data: _Stream) -> str:
    if len(data.t) > 1:
        dt_ms = np.diff(data.t) * 1e3
        keep = _thin(len(dt_ms))
        ax.plot(data.t[1:][keep], dt_ms[keep], lw=0.8, color="tab:green")
    top = 2e3 / data.nominal_hz if data.nominal_hz else 1.0
    if data.nominal_hz:
        ax.axhline(1e3 / data.nominal_hz, color="0.4", lw=0.6, ls="--")
    if len(data.t) > 1:
        top = max(top, 1.1 * float(np.nanmax(dt_ms)))
    ax.set_ylim(0, top)
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.set_ylabel(f"{name}\ninterval (ms)")
    ax.set_title(f"{name}: time between samples (dashed = nominal)", fontsize=9, loc="left")
    return "sample intervals"


def _generic_panel(ax, name: str, data: _Stream, columns: list[str]) -> str:
    drawn = []
    for column in columns:
        values = np.asarray(data.table[column])
        if values.dtype.kind not in "fiu" or column.startswith("t_"):
            continue
        _line(ax, data, values, label=column)
        drawn.append(column)
        if len(drawn) == 6:
            break
    if drawn:
        ax.legend(loc="upper right", fontsize=7, ncol=min(6, len(drawn)))
    ax.set_ylabel(name)
    ax.set_title(f"{name}: {', '.join(drawn) or 'sample times only'}", fontsize=9, loc="left")
    return "columns " + ", ".join(drawn) if drawn else "sample times"


def _label_panel(ax, start: np.ndarray, end: np.ndarray, labels: list[str]) -> None:
    from matplotlib.patches import Patch

    classes = sorted(set(labels) - {""}, key=lambda s: [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", s)])
    cmap = _pyplot().get_cmap("tab20", max(1, len(classes)))
    colour = {c: cmap(i) for i, c in enumerate(classes)}
    values = np.array(labels, dtype=object)
    for label in [*classes, ""]:
        mask = values == label
        spans = [(float(start[a]), float(end[b - 1] - start[a])) for a, b in _runs(mask)]
        if spans:
            ax.broken_barh(spans, (0, 1), color=colour.get(label, UNLABELLED_COLOUR))
    ax.set_yticks([])
    ax.set_ylabel("gestures")
    handles = [Patch(color=colour[c], label=c) for c in classes]
    handles.append(Patch(color=UNLABELLED_COLOUR, label="grey = unlabelled"))
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=7, ncol=1 + len(handles) // 8,
              frameon=False)
    ax.set_title("labels/gestures.csv", fontsize=9, loc="left")


def _shade(ax, gap: Gap) -> None:
    colour = SEQ_GAP_COLOUR if gap.kind == "seq_gap" else OUTAGE_COLOUR
    ax.axvspan(gap.start_s, max(gap.end_s, gap.start_s + 0.05), color=colour, alpha=0.25, lw=0)


def _legend_for_gaps(ax, gaps: list[Gap]) -> None:
    if not gaps:
        return
    from matplotlib.patches import Patch

    handles, labels = ax.get_legend_handles_labels()
    for kind, colour, label in (("seq_gap", SEQ_GAP_COLOUR, "sequence gap"), ("outage", OUTAGE_COLOUR, "device outage")):
        if any(g.kind == kind for g in gaps):
            handles.append(Patch(color=colour, alpha=0.25))
            labels.append(label)
    ax.legend(handles, labels, loc="lower left", fontsize=7, ncol=min(6, len(labels)))
