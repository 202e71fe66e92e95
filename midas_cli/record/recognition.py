"""The recognition process of `midas record --live-model`: rows in, one gesture per frame out.

A worker like the devices' (record/worker.py): forked by the same fork server (which has the model's
modules, torch, preloaded), it ignores the stop signals, talks to the recorder through the same link
(events, bookkeeping of the rows it wrote) and appends its stream, ``gestures_live``, itself (crash-safe
as every stream: whole lines, fsynced by the recorder about once a second; published with
``--lsl-out``). Its "device" is ``recognition``.

Input: the device workers' ``RowFeed`` pipes (record/feed.py). It ends when every one of them has
closed (their workers finished, so every row recorded that reached it has been seen), or when the
recorder is gone. Once it has predicted its first frame (what came while the model loaded is caught up
on), a frame that could only be predicted more than ``LivePlan.max_lag_s`` after its time is skipped
(``LiveFeed.drop_until``, counted): a slow model falls behind by at most that much, and the recording
never waits for it.
"""

from __future__ import annotations

import logging
import sys
import traceback
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any, Callable

from midas_cli.clock import HostClock
from midas_cli.processes import process_alive
from midas_cli.record.link import WorkerLink
from midas_cli.record.live_model import LivePlan, RECOGNITION_DEVICE, RECOGNITION_KIND, gestures_spec
from midas_cli.record.lsl_out import LiveOutlets
from midas_cli.record.worker import StreamWriteFailed, WorkerOutput, freeze_inherited_objects, ignore_stop_signals

log = logging.getLogger(__name__)

POLL_S = 0.05
ALIVE_EVERY_S = 0.5  # how often the loop checks the recorder is still there (a /proc read)
WARN_EVERY_S = 5.0  # at most one "frames skipped" warning this often


@dataclass(frozen=True)
class RecognitionJob:
    plan: LivePlan
    anchor_ns: int
    parent_pid: int
    stream_file: str  # absolute path of gestures_live.csv (created by the recorder)
    session: str  # the session folder's name (LSL source ids)
    queue_size: int = 4096
    lsl_out: bool = False


def recognition_main(job: RecognitionJob, sender: Connection, feeds: list[Connection]) -> None:
    """Entry point of the recognition process (``feeds``: one pipe per device worker that feeds it)."""
    ignore_stop_signals()
    freeze_inherited_objects()
    link = WorkerLink(sender, job.queue_size)
    output = WorkerOutput(RECOGNITION_DEVICE, link, HostClock(job.anchor_ns), every_s=0.0)
    status = 0
    try:
        output.event("opening")
        output.open({gestures_spec(job.plan).name: job.stream_file})
        if job.lsl_out:
            output.outlets = LiveOutlets(job.session, RECOGNITION_KIND, job.anchor_ns,
                                         lambda message: output.event("warning", message))
        model = load_checked(job.plan, output.clock.now_ns)
        output.event("opened", info={"run_id": model.spec.run_id, "model": model.spec.model})
        output.event("finished", info=Recognition(job, output).run(model, feeds))
    except StreamWriteFailed as exc:
        output.event("write_failed", str(exc), {"stream": exc.stream, "rows": exc.rows})
    except Exception:  # a bug or a model that fails: the recording goes on without it
        output.event("crashed", traceback.format_exc())
        status = 1
    output.event("exited")
    output.close()
    link.close()
    if status:
        sys.exit(status)


def load_checked(plan: LivePlan, clock: Callable[[], int]) -> Any:
    """The run's ``LiveFeed`` (its modules are preloaded; ``clock`` stamps its predictions), refused if its
    checkpoint changed since the recording was planned (the manifest would name the wrong one)."""
    from midas_cli.analysis.live_gestures import load_live_model

    model = load_live_model(Path(plan.run), plan.nominal_rates_hz, clock)
    if model.spec.checkpoint_sha256 != plan.checkpoint_sha256:
        raise RuntimeError(f"{plan.run}: the checkpoint changed since the recording was planned")
    return model


class Recognition:
    """The loop: read the feeds, predict every frame that can be, write the predictions."""

    def __init__(self, job: RecognitionJob, output: WorkerOutput) -> None:
        self.job, self.output = job, output
        self.spec = gestures_spec(job.plan)
        self.skipped = 0
        self.predicted = False  # until the first prediction nothing is skipped: what came while loading is not late
        self.rows_dropped: dict[int, int] = {}  # per feed: its running total
        self._warned_ns = 0
        self._warned_skipped = 0

    def run(self, model: Any, feeds: list[Connection]) -> dict[str, Any]:
        """Feed ``model`` (a ``LiveFeed``) until every feed has closed; the counts for the manifest."""
        open_feeds = list(feeds)
        clock = self.output.clock
        checked_ns = clock.now_ns()
        while open_feeds:
            if clock.now_ns() - checked_ns >= ALIVE_EVERY_S * 1e9:
                if not process_alive(self.job.parent_pid):
                    break
                checked_ns = clock.now_ns()
            for conn in wait(open_feeds, POLL_S):
                self._read(conn, model, open_feeds)
            self._predict(model)
        self._predict(model)
        self._write(model.flush())  # a delayed model's last frames (train gestures --delay)
        return {"frames_skipped": self.skipped, "input_rows_dropped": sum(self.rows_dropped.values())}

    def _read(self, conn: Any, model: Any, open_feeds: list[Connection]) -> None:
        try:
            batches, dropped = conn.recv()
        except (EOFError, OSError):
            open_feeds.remove(conn)
            return
        self.rows_dropped[id(conn)] = int(dropped)
        for stream, times, values in batches:
            model.add(stream, times, values)

    def _predict(self, model: Any) -> None:
        """Skip frames too old to be worth predicting, predict the rest, write them."""
        clock = self.output.clock
        if self.predicted:
            self.skipped += model.drop_until(clock.now_ns() - int(self.job.plan.max_lag_s * 1e9))
        predictions = model.ready()
        if predictions:
            self.predicted = True
            self._write(predictions)
        else:
            self.output.tick()
        self._warn_if_skipping(clock.now_ns())

    def _write(self, predictions: list) -> None:
        if predictions:
            t_decoded = self.output.clock.now_ns()
            rows = [(p.seq, p.t_host_ns, p.t_pred_ns, p.label, round(float(p.probability), 4), p.decoded,
                     round(float(p.decoded_probability), 4), t_decoded) for p in predictions]
            self.output.write(self.spec, rows, 0)

    def _warn_if_skipping(self, now_ns: int) -> None:
        if self.skipped > self._warned_skipped and now_ns - self._warned_ns >= WARN_EVERY_S * 1e9:
            self._warned_ns, self._warned_skipped = now_ns, self.skipped
            self.output.event("warning", f"the recognition is behind: {self.skipped} frames skipped so far")
