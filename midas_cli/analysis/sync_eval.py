"""`midas eval sync`: how close in time a session's modalities really are, from what two of them both see.

Every midas stream is stamped with one host clock, but a stamp is taken when the bytes arrive, so each
modality carries its own transport delay (and a sensor its own latency). The offset between two
modalities can only be measured from events both observe:

* ``emht~<robot>``: hand motion. The EmHT hand points and the robot's master (or patient-side) hand
  positions are two views of the same movement; the lag of the EmHT speed profile behind the robot's
  (cross-correlation refined to a fraction of a sample: ``fit_calibration.speed_lag_s``) is the
  offset. It is estimated over the whole session and in ``windows`` equal stretches: their spread is the
  offset's uncertainty and their slope against time the drift between the two (ppm).
* ``pedals_gt~fps``: pedal presses. The pressed states read from the console video
  (``derived/pedals_gt.csv``, `midas extract pedals`) and the pedal board's own pressed states;
  each press onset seen by both (the nearest board onset of the same pedal within ``MATCH_S``) gives
  one offset; their median, spread and slope are reported.

``offset_ms`` is always how late the second modality sees an event than the first; a verdict compares
its magnitude (and the windows' worst) with the user's threshold. Pure analysis: reads sessions, writes
nothing (commands/eval.py renders and writes).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from midas_cli.analysis.evaluation import PEDAL_CHANNELS
from midas_cli.analysis.figures import sync_figure
from midas_cli.analysis.fit_calibration import emht_arrays, robot_arrays, speed_lag_s
from midas_cli.analysis.hand_features import hand_points
from midas_cli.analysis.report import write_tables
from midas_cli.errors import ConfigError, SessionError
from midas_cli.session.derived import output_dir
from midas_cli.session.outputs import out_folder
from midas_cli.session.pedals_gt import pedals_gt_path
from midas_cli.session.reader import Session

MATCH_S = 0.5  # a press onset in one modality matches the other's nearest onset of the same pedal within this
MAX_LAG_S = 0.5
MIN_WINDOW_S = 5.0
ROBOTS = ("mtm", "psm")


@dataclass
class PairOffset:
    """One pair of modalities in one session. Times in ms; ``windows``: (seconds from the session
    start, offset ms) per window or matched event."""

    session: str
    pair: str
    evidence: str
    n: int
    offset_ms: float
    spread_ms: float | None
    drift_ppm: float | None
    worst_ms: float
    verdict: str = ""
    windows: list[tuple[float, float]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        document = asdict(self)
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in document.items()}


def _trend(points: list[tuple[float, float]]) -> tuple[float | None, float | None]:
    """Spread (sd, ms) and drift (ppm: ms of offset per s of session, x1000) of (t_s, offset_ms) points."""
    if len(points) < 2:
        return None, None
    t, ms = np.array(points).T
    spread = float(np.std(ms, ddof=1))
    if len(points) < 3 or np.ptp(t) <= 0:
        return spread, None
    slope_ms_per_s = float(np.polyfit(t, ms, 1)[0])
    return spread, slope_ms_per_s * 1e3  # 1 ms per s = 1000 ppm


def motion_offset(session: Session, robot: str, windows: int) -> PairOffset | None:
    """EmHT hand motion against the robot's (None when the session lacks either stream)."""
    if "emht" not in session.stream_names or robot not in session.stream_names:
        return None
    robot_t, robot_pos, _ = robot_arrays(session, robot)
    em_t, em_pos, _ = emht_arrays(session)
    points = hand_points(em_pos)
    whole = speed_lag_s(robot_t, robot_pos, em_t, points, MAX_LAG_S) * 1e3
    start_ns = session.manifest["start"]["host_ns"]
    span = (max(robot_t[0], em_t[0]), min(robot_t[-1], em_t[-1]))
    count = max(1, min(windows, int((span[1] - span[0]) / 1e9 // MIN_WINDOW_S)))
    edges = np.linspace(span[0], span[1], count + 1).astype(np.int64)
    found = []
    for a, b in zip(edges[:-1], edges[1:]):
        keep_r = (robot_t >= a) & (robot_t <= b)
        keep_e = (em_t >= a - MAX_LAG_S * 1e9) & (em_t <= b + MAX_LAG_S * 1e9)
        try:
            lag = speed_lag_s(robot_t[keep_r], {h: p[keep_r] for h, p in robot_pos.items()}, em_t[keep_e],
                              {h: p[keep_e] for h, p in points.items()}, MAX_LAG_S)
        except (SessionError, ValueError):
            continue
        found.append(((a + b) / 2e9 - start_ns / 1e9, lag * 1e3))
    spread, drift = _trend(found) if count > 1 else (None, None)
    worst = max([abs(whole), *(abs(ms) for _, ms in found)])
    return PairOffset(session.manifest["session_id"], f"{robot}~emht",
                      f"hand speed cross-correlation ({len(found)} windows)", len(found), whole, spread, drift,
                      worst, windows=found)


def _onsets(t_ns: np.ndarray, pressed: np.ndarray) -> np.ndarray:
    """Host times (ns) where a pressed state goes 0 -> 1 (NaN = unknown: never an onset)."""
    state = np.nan_to_num(np.asarray(pressed, float), nan=-1)
    rising = (state[1:] == 1) & (state[:-1] == 0)
    return np.asarray(t_ns, np.int64)[1:][rising]


def pedal_offset(session: Session) -> PairOffset | None:
    """Press onsets in the console video (pedals_gt) against the pedal board's (None without both)."""
    gt_path = pedals_gt_path(session.path)
    if "fps" not in session.stream_names or not gt_path.is_file():
        return None
    try:
        gt = pd.read_csv(gt_path).dropna(subset=["t_host_ns"]).sort_values("t_host_ns")
    except (ValueError, KeyError) as exc:
        raise SessionError(f"{gt_path}: not a pedal ground-truth table ({exc})") from exc
    board = session.read_columns("fps")
    order = np.argsort(board["t_host_ns"], kind="stable")
    start_ns = session.manifest["start"]["host_ns"]
    found: list[tuple[float, float]] = []
    for pedal, channel in PEDAL_CHANNELS.items():
        name = f"ch{channel}_pressed"
        if pedal not in gt.columns or name not in (board.dtype.names or ()):
            continue
        video = _onsets(gt["t_host_ns"].to_numpy(np.int64), gt[pedal].to_numpy(float))
        device = _onsets(board["t_host_ns"][order], board[name][order])
        for t in video:
            if len(device) == 0:
                break
            nearest = device[np.argmin(np.abs(device - t))]
            if abs(nearest - t) <= MATCH_S * 1e9:
                found.append(((t - start_ns) / 1e9, (nearest - t) / 1e6))
    if not found:
        return None
    found.sort()
    spread, drift = _trend(found)
    offsets = [ms for _, ms in found]
    return PairOffset(session.manifest["session_id"], "pedals_gt~fps", f"press onsets ({len(found)} matched)",
                      len(found), float(np.median(offsets)), spread, drift, float(np.max(np.abs(offsets))),
                      windows=found)


def session_offsets(path: Path | str, windows: int = 6) -> list[PairOffset]:
    """Every pair the session can measure; SessionError when it can measure none."""
    session = Session.open(path)
    pairs = [motion_offset(session, robot, windows) for robot in ROBOTS]
    pairs.append(pedal_offset(session))
    found = [p for p in pairs if p is not None]
    if not found:
        raise SessionError(f"{session.path}: nothing two modalities both see: eval sync needs emht with a robot "
                           "stream (mtm/psm), or the pedal board with derived/pedals_gt.csv")
    return found


def judge(pair: PairOffset, threshold_ms: float) -> PairOffset:
    """Set ``verdict``: ok when the offset and every window's stay within ``threshold_ms``."""
    pair.verdict = "ok" if pair.worst_ms <= threshold_ms else f"over {threshold_ms:g} ms"
    return pair


def run_sync(paths: list[Path], out: Path | None, threshold_ms: float, windows: int, plots: bool,
             progress: Callable[[str], None] = lambda _: None) -> tuple[list[PairOffset], list[Path]]:
    """Every session's pairs judged against ``threshold_ms``; writes the table (``sync.csv|md|tex|json``
    into ``out``, or the one session's derived/eval/) and, with ``plots``, derived/plots/sync.png per
    session. Returns the pairs and the files written."""
    if not (math.isfinite(threshold_ms) and threshold_ms > 0):
        raise ConfigError(f"--threshold-ms must be a finite number of ms > 0, got {threshold_ms}")
    if windows < 1:
        raise ConfigError(f"--windows must be >= 1, got {windows}")
    if out is None and len(paths) != 1:
        raise ConfigError("several sessions given: say where the table goes with --out DIR")
    out_dir = out_folder(out) if out is not None else output_dir(paths[0], "eval")
    pairs: list[PairOffset] = []
    files: list[Path] = []
    for path in paths:
        progress(Path(path).name)
        found = [judge(p, threshold_ms) for p in session_offsets(path, windows)]
        pairs += found
        if plots:
            files.append(sync_figure([(p.pair, p.windows, p.offset_ms) for p in found], threshold_ms,
                                     output_dir(path, "plots") / "sync.png", f"{found[0].session}: offsets between modalities"))
    rows = [{k: v for k, v in p.to_json().items() if k != "windows"} for p in pairs]
    table = pd.DataFrame(rows, columns=["session", "pair", "evidence", "n", "offset_ms", "spread_ms", "drift_ppm",
                                        "worst_ms", "verdict"])
    provenance = {"data_label": f"{len(paths)} session(s)", "sessions": [str(p) for p in paths],
                  "threshold_ms": threshold_ms, "windows": windows,
                  "meaning": "offset_ms: how late the second modality of the pair sees an event than the first"}
    files += write_tables(out_dir, "sync", {"sync": (table, f"Offsets between modalities (threshold {threshold_ms:g} ms)")},
                          {"sync": [p.to_json() for p in pairs]}, provenance)
    return pairs, files
