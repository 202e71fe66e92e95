"""`midas eval live`: how the gestures recognised while recording (the stream ``gestures_live``, `midas
record --live-model`) compare with the session's labels and with the same causal model run offline.

On the live stream's own frames (its ``t_host_ns``): frame accuracy (frames the reference labels),
segmental edit score, and per reference segment whether and when it was detected: the delay from the
segment's first frame to the first live frame inside it with its class (frame time; a segment never
predicted in its span is "missed"). Both classes a row carries are scored: ``class`` (the network's
own) and, where the stream has it, ``decoded`` (the run's clean-up run live; offline reference: the same
decoding of the offline outputs). Each one's latency comes beside (``t_pred_ns`` or ``t_decoded_ns`` -
``t_host_ns``). The labels are per video frame (labels/<set>.csv: frame = seq of the video stream); a live frame
takes the label of the latest video frame at or before it. The offline reference is
``live_gestures.offline_predictions`` on the recorded streams, with the run the manifest names and the
nominal rates the live model was given (how old a sample may be and still count).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.errors import ConfigError, SessionError
from midas_cli.models.metrics import IGNORE, edit_score, segments
from midas_cli.session.labels import list_label_sets, read_frame_labels
from midas_cli.session.reader import Session

LIVE_STREAM = "gestures_live"


@dataclass(frozen=True)
class Agreement:
    """The live classes against one reference ("labels" or "offline") on the live frames."""

    reference: str
    prediction: str  # which live column: "class" (the network's own) or "decoded"
    frames: int  # live frames the reference labels
    accuracy: float | None
    edit: float | None
    segments: int  # reference segments on those frames
    detected: int  # of them, predicted live within their span
    delay_ms: dict[str, float | None]  # detection delay of the detected ones: p50, p90, max


@dataclass(frozen=True)
class LiveEvaluation:
    session: str
    run_id: str
    frames: int  # rows of gestures_live
    skipped: int  # frames the recognition said it skipped
    latency_ms: dict[str, dict[str, float | None]]  # per prediction column: its time - t_host: p50, p99, max
    agreements: tuple[Agreement, ...]

    def to_json(self) -> dict[str, Any]:
        from dataclasses import asdict

        return asdict(self)


def evaluate_live(session_path: Path, run: Path | None = None, label_set: str = "gestures") -> LiveEvaluation:
    """Compare ``gestures_live`` of the session with its label set (when it has one) and with the offline
    model (``run``, default: the one the manifest names). SessionError without the stream."""
    session = Session.open(session_path)
    if LIVE_STREAM not in session.manifest["streams"]:
        raise SessionError(f"{session.path} has no {LIVE_STREAM} stream (record it with `midas record --live-model`)")
    live = session.read_stream(LIVE_STREAM)
    times = live["t_host_ns"].to_numpy(np.int64)
    model = session.manifest["streams"][LIVE_STREAM].get("live_model") or {}
    columns = {"class": "t_pred_ns", "decoded": "t_decoded_ns"}
    columns = {name: time for name, time in columns.items() if name in live.columns and time in live.columns}
    truth = labels_at(session, times, label_set) if label_set in list_label_sets(session.path) else None
    offline = _offline(session, run, model, times)
    agreements, latency = [], {}
    for name, time in columns.items():
        predicted = live[name].fillna("").astype(str).to_numpy(dtype=object)
        if truth is not None:
            agreements.append(agreement("labels", name, predicted, truth, times))
        agreements.append(agreement("offline", name, predicted, offline[name], times))
        latency[name] = _percentiles((live[time].to_numpy(np.int64) - times) / 1e6, (50, 99))
    return LiveEvaluation(session.path.name, str(model.get("run_id", "")), len(live), int(model.get("frames_skipped") or 0),
                          latency, tuple(agreements))


def _offline(session: Session, run: Path | None, model: dict[str, Any], times: np.ndarray) -> dict[str, np.ndarray]:
    """The offline causal model's classes at ``times``, its own (``class``) and decoded (``decoded``);
    ConfigError when there is no run to use."""
    from midas_cli.analysis.live_gestures import offline_predictions

    named = run if run is not None else model.get("run")
    if not isinstance(named, (str, Path)) or not Path(named).exists():
        raise ConfigError(f"{session.path}: the run of its live model ({named!r}) is not here: give --run RUN")
    rates = model.get("nominal_rates_hz")  # what the live model was given: the same for equal frames
    if not (isinstance(rates, dict) and all(isinstance(r, (int, float, type(None))) for r in rates.values())):
        rates = None
    predictions = offline_predictions(session.path, Path(named), times, rates)
    return {"class": np.asarray([p.label for p in predictions], dtype=object),
            "decoded": np.asarray([p.decoded for p in predictions], dtype=object)}


def labels_at(session: Session, times: np.ndarray, label_set: str) -> np.ndarray:
    """The label ('' = none) of the latest video frame at or before each of ``times`` (host ns)."""
    labels = read_frame_labels(session.path, label_set)
    video = session.read_stream("video")
    frame_t = video["t_host_ns"].to_numpy(np.int64)
    frame_seq = video["seq"].to_numpy(np.int64)
    by_seq = dict(zip(labels.frames.tolist(), labels.labels.tolist()))
    at = np.searchsorted(frame_t, times, side="right") - 1
    return np.asarray(["" if k < 0 else str(by_seq.get(int(frame_seq[k]), "") or "") for k in at], dtype=object)


def agreement(reference: str, prediction: str, live: np.ndarray, truth: np.ndarray, times: np.ndarray) -> Agreement:
    """``live`` (the column ``prediction``) against ``truth`` (class text per frame, '' = unlabelled) on
    frames at ``times`` (ns)."""
    names = sorted((set(live.tolist()) | set(truth.tolist())) - {""})
    index = {name: k for k, name in enumerate(names)}
    pred = np.asarray([index.get(c, IGNORE) for c in live])
    true = np.asarray([IGNORE if c == "" else index[c] for c in truth])
    labelled = true != IGNORE
    if not labelled.any():
        return Agreement(reference, prediction, 0, None, None, 0, 0, _percentiles(np.zeros(0), (50, 90)))
    delays = detection_delays_ms(pred, true, times)
    found = np.asarray([d for d in delays if d is not None])
    return Agreement(reference, prediction, int(labelled.sum()), round(float((pred[labelled] == true[labelled]).mean()), 4),
                     round(edit_score(pred[labelled], true[labelled]), 2), len(delays), len(found),
                     _percentiles(found, (50, 90)))


def detection_delays_ms(pred: np.ndarray, truth: np.ndarray, times: np.ndarray) -> list[float | None]:
    """Per segment of ``truth``: ms from its first frame to the first frame inside it that ``pred`` gives
    its class (None: never within the segment)."""
    runs = segments(truth)
    delays: list[float | None] = []
    for label, start, end in zip(runs.labels, runs.starts, runs.ends):
        hits = np.flatnonzero(pred[start:end] == label)
        delays.append(None if not len(hits) else (int(times[start + hits[0]]) - int(times[start])) / 1e6)
    return delays


def _percentiles(values: np.ndarray, which: tuple[int, ...]) -> dict[str, float | None]:
    if not len(values):
        return {**{f"p{q}": None for q in which}, "max": None}
    return {**{f"p{q}": round(float(np.percentile(values, q)), 3) for q in which}, "max": round(float(values.max()), 3)}
