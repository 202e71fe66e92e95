"""`midas record --live-model RUN`: what the recording needs to know about a gesture model run live.

The model itself is analysis/live_gestures.py (``load_live_model``, ``LiveFeed``); this module checks,
before anything is recorded, that the rig gives every stream and column the model was trained on, and
describes the session's ``gestures_live`` stream: one row per frame of the model's frame clock,
``seq`` (the frame's index on that clock: a gap is a frame the recognition skipped to catch up),
``t_host_ns`` (the frame's time, host clock), ``t_pred_ns`` (host clock when its prediction was made),
``class`` (the network's most probable class, label text) and ``probability``; ``decoded``,
``decoded_probability`` (the run's clean-up run live: no segment shorter than its minimum, the training
gesture order; what the screen shows) and ``t_decoded_ns`` (host clock when the row was handed over:
the decoded class is decided ``--decode-lag`` after ``t_pred_ns``). A model trained with ``--delay``
labels each frame that much later (its ``t_pred_ns`` - ``t_host_ns`` includes it; the manifest's
``live_model`` says ``delay_s`` and, under ``decoding``, the decoding's minimum and lag).
Its rows are written by the recognition process
(record/recognition.py), a worker like the devices' (its own device ``recognition``), fed with the rows of
the streams it needs by the device workers (record/feed.py) without ever making one of them wait.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

from midas_cli.errors import ConfigError
from midas_cli.record.status import GestureStatus
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec

GESTURES_STREAM = "gestures_live"
RECOGNITION_DEVICE = "recognition"
RECOGNITION_KIND = "gestures"
MODEL_MODULE = "midas_cli.analysis.live_gestures"  # preloaded by the workers' fork server (torch: once)
LATENCY_DEFINITION = ("the frame's time (t_host_ns) -> its row handed to the OS: the inputs' arrival, the feed's "
                      "batching, the model and the decoding's lag, upper edge of 50 us bins")
MAX_LAG_S = 1.0  # a frame older than this when it could be predicted is skipped (counted), not predicted


@dataclass(frozen=True)
class LivePlan:
    """A live model checked against the rig (picklable: it goes to the recognition process).
    ``streams``: stream name -> the columns the model reads from it, in the model's order."""

    run: str
    run_id: str
    checkpoint_sha256: str
    model: str
    rate_hz: float
    streams: dict[str, tuple[str, ...]]
    classes: tuple[str, ...]
    max_lag_s: float = MAX_LAG_S
    nominal_rates_hz: dict[str, float | None] = field(default_factory=dict)  # the rig's, of ``streams``: staleness
    delay_frames: int = 0  # the model labels a frame this many frames late (train gestures --delay)
    decoding: dict[str, Any] = field(default_factory=dict)  # live_features.Decoding.manifest()

    def manifest(self) -> dict[str, Any]:
        """The ``live_model`` entry of the ``gestures_live`` stream (counts are added at the stop)."""
        return {"run": self.run, "run_id": self.run_id, "checkpoint_sha256": self.checkpoint_sha256,
                "model": self.model, "rate_hz": self.rate_hz, "classes": list(self.classes),
                "inputs": {name: list(columns) for name, columns in self.streams.items()},
                "nominal_rates_hz": dict(self.nominal_rates_hz), "max_lag_s": self.max_lag_s,
                "delay_frames": self.delay_frames, "delay_s": round(self.delay_frames / self.rate_hz, 6),
                "decoding": dict(self.decoding)}


def plan_live_model(run: Path) -> LivePlan:
    """Load the run's model once (ConfigError, exit 2, when it cannot run live) and describe it."""
    from midas_cli.analysis.live_gestures import load_live_model  # torch: only when asked for

    feed = load_live_model(run)
    spec = feed.spec
    return LivePlan(str(Path(run).resolve()), spec.run_id, spec.checkpoint_sha256, spec.model, float(spec.rate_hz),
                    {name: tuple(columns) for name, columns in spec.streams.items()}, tuple(spec.classes),
                    delay_frames=feed.delay, decoding=feed.live.decoding.manifest())


def check_rig_streams(plan: LivePlan, specs: Mapping[str, StreamSpec], devices: Mapping[str, Any]) -> LivePlan:
    """``plan`` with the rig's nominal rates of its streams (how old a sample may be and still count, as
    in ``align``); ConfigError (one line) naming every stream or column the model needs and the rig does
    not record. ``specs``: the rig's streams by name; ``devices``: its device names (neither may take the
    recognition's)."""
    if GESTURES_STREAM in specs or RECOGNITION_DEVICE in devices:
        raise ConfigError(f"--live-model writes the stream {GESTURES_STREAM!r} of device {RECOGNITION_DEVICE!r}: "
                          f"rename the rig's device or stream of that name")
    missing = []
    for name, columns in plan.streams.items():
        if name not in specs:
            missing.append(f"stream {name}")
            continue
        absent = [c for c in columns if c not in specs[name].column_names]
        if absent:
            missing.append(f"{name} columns {', '.join(absent)}")
    if missing:
        raise ConfigError(f"--live-model {plan.run} (run {plan.run_id}) needs what this rig does not record: "
                          f"{'; '.join(missing)} (EmHT comes from the rig, MTM/PSM from raven://, any from lsl://)")
    return replace(plan, nominal_rates_hz={name: specs[name].nominal_rate_hz for name in plan.streams})


def live_stream_extra(plan: LivePlan, info: Mapping[str, Any], extra: dict[str, Any]) -> None:
    """Complete the recorder's facts about ``gestures_live`` (``extra``, changed in place) at the stop:
    ``live_model`` (the run, its checkpoint, and the recognition's counts from its ``finished`` event,
    ``info``: frames skipped, input rows it never got), the skipped frames as explained seq gaps, and
    what its latency measures."""
    counts = {key: info.get(key) for key in ("frames_skipped", "input_rows_dropped")}
    extra["live_model"] = {**plan.manifest(), **counts}
    extra["missing_explained"] = {**extra.get("missing_explained", {}), "skipped": counts["frames_skipped"] or 0}
    if extra.get("latency_ms"):
        extra["latency_ms"]["definition"] = LATENCY_DEFINITION


def gestures_spec(plan: LivePlan) -> StreamSpec:
    """The ``gestures_live`` stream's layout (a regular stream at the model's frame rate); as a marker
    stream (``--lsl-out``, an XDF export) it is the decoded gesture, what the live screen shows."""
    return StreamSpec(GESTURES_STREAM, RECOGNITION_DEVICE, (
        Column(SEQ.name, "int", "count", description="frame index on the model's frame clock (gaps: frames skipped)"),
        Column(T_HOST.name, "int", "ns", clock="host", description="the frame's time on the model's frame clock"),
        Column("t_pred_ns", "int", "ns", clock="host", description="host clock when the frame was predicted"),
        Column("class", "text", description="the predicted gesture (label text)"),
        Column("probability", "float", "", 4, description="the model's probability of that class"),
        Column("decoded", "text", description="the gesture the run's clean-up decided, run live (what the screen "
                                              "shows)"),
        Column("decoded_probability", "float", "", 4, description="the model's probability of the decoded class"),
        Column("t_decoded_ns", "int", "ns", clock="host", description="host clock when the row was handed over "
                                                                      "(decoded class decided)"),
    ), plan.rate_hz, f"gestures recognised live by run {plan.run_id} ({plan.model})", marker="decoded")


class GestureTracker:
    """The recorder's view of the recognition: the current gesture, since when, and how late.

    It sees the last row of each batch the recognition process wrote (one batch per pass of its loop:
    usually one frame), so a gesture's start is that of the first frame seen with it."""

    def __init__(self, rate_hz: float) -> None:
        self.period_s = 1.0 / rate_hz
        self.label: str | None = None
        self.probability = 0.0
        self.since_ns = self.last_ns = self.decided_ns = 0

    def update(self, last_row: tuple) -> None:
        """``last_row``: a ``gestures_live`` row (seq, t_host_ns, t_pred_ns, class, probability, decoded,
        decoded_probability, t_decoded_ns) of the latest prediction: the decoded class is shown."""
        t_host_ns, label, probability, t_decoded_ns = last_row[1], last_row[5], last_row[6], last_row[7]
        if label != self.label:
            self.label, self.since_ns = label, int(t_host_ns)
        self.last_ns, self.decided_ns, self.probability = int(t_host_ns), int(t_decoded_ns), float(probability)

    def status(self, now_ns: int) -> GestureStatus | None:
        """What the screen and `midas ctl status` show (None before the first prediction)."""
        if self.label is None:
            return None
        return GestureStatus(self.label, round(self.probability, 4),
                             round((self.last_ns - self.since_ns) / 1e9 + self.period_s, 3),
                             round((self.decided_ns - self.last_ns) / 1e6, 1), round((now_ns - self.decided_ns) / 1e9, 3))
