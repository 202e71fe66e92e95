"""Gestures recognised while recording (issue 28): a causal model from a training run, fed with stream
rows as they arrive, predicts each frame of its own clock once that frame's inputs are known.

``load_live_model(run)`` checks the run can run live and returns a ``LiveFeed``; ``LiveFeed.add`` takes
rows of a stream (host ns, values in the columns ``spec.streams`` names), ``ready()`` returns every frame
that can now be predicted, in order, each in constant time (``models/streaming.py``: incremental
state, no window re-run), and ``drop_until`` skips frames a slow model cannot catch up with (their seq
numbers are left out; the model then continues as if those frames had not been, so its later
predictions may differ from offline ones).

The frame clock: multiples of 1 / ``rate_hz`` on the host clock (ns), starting at the first one whose
inputs every stream has (a sample at or before t - s, see ``analysis/live_features.py`` for s and how a
frame's features are built from the streams as ``align`` associates them). A frame is computed once
every stream has a sample after t + s: rows of a stream must come in time order, and a stream that stops
holds recognition up (the caller decides to ``drop_until``).

A model trained with ``--delay`` (``delay`` frames) labels the frame it stepped ``delay`` steps before: its
predictions come that much later; ``flush()`` at the end steps ``delay`` zero frames (as the offline forward
pass appends them, models/mstcn.py ``look_ahead``) for the frames still waiting.

Each prediction carries two classes: the network's own (``label``, the most probable class of that frame)
and the run's clean-up run live (``decoded``: ``live_features.Decoding``, the best labelling so far with
segments no shorter than the run's minimum and the training gesture order, each frame decided the run's
``--decode-lag`` frames after it; the metrics of a causal run measure it). A prediction is handed out
once both are known: ``decode_lag`` frames after its network output.

``offline_predictions(session, run, times)`` runs the same model over a recorded session the offline
way (one forward pass of the whole sequence, on features built the same way, then the run's decoding):
live and offline classes, and decoded classes where no frame was skipped, agree frame for frame
(tests/analysis/test_live_gestures.py).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Mapping

import numpy as np
import torch

from midas_cli.analysis.live_features import (FrameClock, FrameInputs, LiveRun, associated, load_run, stale_ns)
from midas_cli.errors import ConfigError, SessionError
from midas_cli.models.streaming import frame_stepper
from midas_cli.session.reader import Session


@dataclass(frozen=True)
class Prediction:
    seq: int  # 0, 1, 2, ... per frame of the live frame clock (frames skipped by drop_until leave gaps)
    t_host_ns: int  # the frame's time (host clock) on the model's frame clock
    class_index: int
    label: str  # class name, e.g. "G1"
    probability: float  # softmax of the last stage's logits at the predicted class
    decoded: str = ""  # the decoded class (the run's clean-up run live; "" until decided)
    decoded_probability: float = 0.0  # that softmax at the decoded class
    t_pred_ns: int = 0  # when the network's output was known (the feed's clock; 0 without one)


@dataclass(frozen=True)
class LiveSpec:
    run_id: str  # the run folder's name
    checkpoint_sha256: str
    model: str  # registry name, e.g. "mstcn"
    rate_hz: float  # the model's frame rate (its --model-rate)
    streams: dict[str, tuple[str, ...]]  # stream name (as in a session) -> the stream's columns it needs
    classes: tuple[str, ...]


class StreamBuffer:
    """The rows of one stream still needed: host times (M,) ascending and values (M, C)."""

    def __init__(self, n_columns: int) -> None:
        self.t_ns = np.zeros(0, dtype=np.int64)
        self.values = np.zeros((0, n_columns))
        self.first_ns: int | None = None

    def add(self, t_ns: np.ndarray, values: np.ndarray) -> None:
        t = np.concatenate([self.t_ns, t_ns])
        v = np.concatenate([self.values, values])
        if len(t) > 1 and (np.diff(t) < 0).any():  # rows out of order: as align, in time order
            order = np.argsort(t, kind="stable")
            t, v = t[order], v[order]
        self.t_ns, self.values = t, v
        if self.first_ns is None and len(t):
            self.first_ns = int(t[0])

    def last_ns(self) -> int | None:
        return int(self.t_ns[-1]) if len(self.t_ns) else None

    def forget_before(self, t_ns: int) -> None:
        """Keep the latest row at or before ``t_ns`` and every later one."""
        keep = max(0, int(np.searchsorted(self.t_ns, t_ns, side="right")) - 1)
        if keep:
            self.t_ns, self.values = self.t_ns[keep:], self.values[keep:]


class LiveFeed:
    """Stream rows in, frame predictions out; see the module docstring."""

    def __init__(self, live: LiveRun, nominal_rates_hz: Mapping[str, float | None] | None = None,
                 clock: Callable[[], int] | None = None) -> None:
        self.live = live
        self._now = clock or (lambda: 0)
        self.spec = LiveSpec(live.run_id, live.checkpoint_sha256, live.model_name, live.rate_hz, live.streams,
                             live.classes)
        rates = dict(nominal_rates_hz or {})
        self._stale = {s: stale_ns(rates.get(s)) for s in self.spec.streams}
        self._buffers = {s: StreamBuffer(len(cols)) for s, cols in self.spec.streams.items()}
        self._stepper = frame_stepper(live.model)
        self._inputs = FrameInputs(live)
        self._clock = FrameClock(live.rate_hz)
        self._first: int | None = None  # clock index of the first frame (seq 0)
        self._next: int | None = None  # clock index of the next frame to predict
        self.delay = int(getattr(live.model.cfg, "delay", 0))  # frames: a frame is labelled this many steps late
        self._waiting: deque[int] = deque()  # clock indices stepped, not labelled yet (at most ``delay``)
        self._steps = 0  # frames stepped (zeros of flush() included)
        self._dim = 0  # the model's input size (flush steps zero vectors of it)
        self._decoder = live.decoding.decoder(len(live.classes))
        self._undecided: deque[tuple[Prediction, np.ndarray]] = deque()  # (prediction, its probabilities)

    def add(self, stream: str, t_host_ns: np.ndarray, values: np.ndarray) -> None:
        """Rows of one stream as recorded (t_host_ns (n,), values (n, len(spec.streams[stream])) in that
        column order). A stream the model does not need is ignored."""
        if stream not in self._buffers:
            return
        t = np.asarray(t_host_ns, dtype=np.int64).reshape(-1)
        v = np.asarray(values, dtype=np.float64)
        columns = self.spec.streams[stream]
        if v.size != len(t) * len(columns):
            raise ConfigError(f"live gestures: {len(t)} {stream} rows came with {v.size} values, the model needs "
                              f"{len(columns)} a row ({', '.join(columns)})")
        self._buffers[stream].add(t, v.reshape(len(t), len(columns)))

    def ready(self) -> list[Prediction]:
        """Every frame that can now be computed, predicted in order."""
        known = [b.first_ns for b in self._buffers.values() if b.first_ns is not None]
        if self._next is None and len(known) == len(self._buffers):
            self._first = self._next = self._clock.first_at_or_after(max(known) + self._inputs.step_ns)
        out = []
        while self._next is not None and self._computable(self._clock.time(self._next)):
            out.extend(self._predict(self._next))
            self._next += 1
        self._forget()
        return out

    def flush(self) -> list[Prediction]:
        """The end of the input: the frames still waiting for their label (a delayed model), labelled from
        zero frames after the last one, as the offline forward pass does, then every frame still waiting
        for its decoded class, decided as the sequence ends. Nothing to add after it."""
        out = []
        while self._waiting:
            out.extend(self._labelled(self._stepper.step(np.zeros(self._dim))))
        return out + (self._decided(self._decoder.finish()) if self._undecided else [])

    def drop_until(self, t_host_ns: int) -> int:
        """Skip frames older than ``t_host_ns`` (a slow model catching up); how many were skipped."""
        if self._next is None:
            return 0
        target = self._clock.first_at_or_after(int(t_host_ns))
        skipped = max(0, target - self._next)
        self._next += skipped
        self._forget()
        return skipped

    def _computable(self, t_ns: int) -> bool:
        """Every stream has a row after t + s: the rows at t - s, t, t + s are final."""
        last = [b.last_ns() for b in self._buffers.values()]
        return all(x is not None and x > t_ns + self._inputs.step_ns for x in last)

    def _predict(self, k: int) -> list[Prediction]:
        """Step frame ``k``: its prediction, or (delayed model) the one of the frame stepped ``delay`` before."""
        t_ns = self._clock.time(k)
        times = t_ns + np.array([-self._inputs.step_ns, 0, self._inputs.step_ns], dtype=np.int64)
        rows = np.concatenate([associated(b.t_ns, b.values, times, self._stale[s]) for s, b in self._buffers.items()],
                              axis=1)  # (3, C): the streams' columns in spec order
        x = self._inputs(t_ns, rows)
        self._dim = len(x)
        self._waiting.append(k)
        return self._labelled(self._stepper.step(x))

    def _labelled(self, logits: np.ndarray) -> list[Prediction]:
        """The step just taken gives the label of the frame stepped ``delay`` steps before it (if any)."""
        self._steps += 1
        if self._steps <= self.delay:
            return []
        k = self._waiting.popleft()
        prediction = _prediction(k - (self._first or 0), self._clock.time(k), logits, self.spec.classes, self._now())
        log_probs = _log_softmax(logits)
        self._undecided.append((prediction, np.exp(log_probs)))
        return self._decided(self._decoder.step(log_probs))

    def _decided(self, labels: list[int]) -> list[Prediction]:
        """The oldest undecided predictions, one per decoded label (oldest first), made whole."""
        out = []
        for index in labels:
            prediction, probs = self._undecided.popleft()
            out.append(replace(prediction, decoded=self.spec.classes[index], decoded_probability=float(probs[index])))
        return out

    def _forget(self) -> None:
        """Drop rows no frame to come needs: before the next frame's first row time, or before the first
        sample of the stream that started last (frames start after it)."""
        if self._next is not None:
            keep_from = self._clock.time(self._next) - self._inputs.step_ns
        else:
            known = [b.first_ns for b in self._buffers.values() if b.first_ns is not None]
            if not known:
                return
            keep_from = max(known)
        for buffer in self._buffers.values():
            buffer.forget_before(keep_from)


def _log_softmax(logits: np.ndarray) -> np.ndarray:
    shifted = np.asarray(logits, dtype=np.float64) - np.max(logits)
    return shifted - np.log(np.exp(shifted).sum())


def _prediction(seq: int, t_ns: int, logits: np.ndarray, classes: tuple[str, ...], t_pred_ns: int = 0) -> Prediction:
    e = np.exp(logits - logits.max())
    index = int(np.argmax(logits))
    return Prediction(seq, int(t_ns), index, classes[index], float(e[index] / e.sum()), t_pred_ns=int(t_pred_ns))


def load_live_model(run: Path, nominal_rates_hz: Mapping[str, float | None] | None = None,
                    clock: Callable[[], int] | None = None) -> LiveFeed:
    """RUN = a training run folder (or its checkpoint.pt); ConfigError (exit 2, one line) when it cannot run
    live. ``nominal_rates_hz`` (stream -> its nominal rate, None = events) sets how old a sample may be
    and still count, as align's (3 periods; 1 s for a stream not given: the latest sample is held through
    an outage shorter than that). ``clock`` (host ns) stamps each prediction's ``t_pred_ns``."""
    return LiveFeed(load_run(run), nominal_rates_hz, clock)


def offline_predictions(session: Path, run: Path, times_ns: np.ndarray,
                        nominal_rates_hz: Mapping[str, float | None] | None = None) -> list[Prediction]:
    """The same causal model run offline (the whole sequence, one forward pass) on features built from the
    session's recorded streams at the frame times ``times_ns`` (ascending host ns), seq = their index.
    ``nominal_rates_hz`` as for ``load_live_model``: give both the same (or neither) for equal frames."""
    recorded = Session.open(session)
    live = load_run(run)
    missing = [s for s in live.streams if s not in recorded.stream_names]
    if missing:
        raise SessionError(f"{session} has no {', '.join(missing)} stream: the model {live.run_id} needs it")
    times = np.asarray(times_ns, dtype=np.int64)
    if not len(times):
        return []
    inputs = FrameInputs(live)
    around = (times[:, None] + np.array([-inputs.step_ns, 0, inputs.step_ns])).reshape(-1)  # (T, 3) -> (3T,)
    blocks = []
    for stream, columns in live.streams.items():
        data = recorded.read_columns(stream)
        t = np.asarray(data["t_host_ns"], dtype=np.int64)
        order = np.argsort(t, kind="stable")
        values = np.column_stack([np.asarray(data[c], dtype=np.float64) for c in columns])[order]
        blocks.append(associated(t[order], values, around, stale_ns((nominal_rates_hz or {}).get(stream))))
    rows = np.concatenate(blocks, axis=1).reshape(len(times), 3, -1)  # (3T, C) -> (T, 3, C)
    x = np.stack([inputs(int(t), r) for t, r in zip(times, rows)])  # (T, D) float32, frames in order
    with torch.no_grad():
        stages = live.model(torch.from_numpy(x.T[None].copy()), torch.ones(1, len(times), dtype=torch.bool))
    logits = live.model.frame_logits(stages)[0].numpy().T.astype(np.float64)  # (C, T) -> (T, C)
    probs = np.stack([np.exp(_log_softmax(row)) for row in logits])
    decoded = live.decoding.offline(np.stack([_log_softmax(row) for row in logits]).T)
    return [replace(_prediction(k, int(t), logits[k], live.classes), decoded=live.classes[d],
                    decoded_probability=float(probs[k, d])) for k, (t, d) in enumerate(zip(times, decoded))]
