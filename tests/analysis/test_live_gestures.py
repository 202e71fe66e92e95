"""Live gesture recognition (analysis/live_gestures.py, issue 28): a tiny causal model trained on simulated
labelled sessions, fed one session's stream rows in chunks of random size, predicts every frame of its
clock exactly as the same model run offline over the recorded session; what cannot run live is refused."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers.cli import midas
from midas_cli.analysis.align import align_and_write
from midas_cli.analysis.live_features import FrameClock, feature_step_ns
from midas_cli.analysis.live_gestures import LiveFeed, load_live_model, offline_predictions
from midas_cli.errors import ConfigError
from midas_cli.models.data import DatasetConfig
from midas_cli.models.train import TrainConfig, train_run
from midas_cli.session.reader import Session

TINY = {"mstcn": {"pg_layers": 5, "refinement_stages": 1, "refinement_layers": 4, "feature_maps": 12},
        "transformer": {"cnn_channels": 8, "d_model": 16, "n_heads": 2, "ff_dim": 16, "window": 16,
                        "refinement_layers": 4, "refinement_maps": 8}}


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("live")
    result = midas("simulate", "dataset", "--platform", "raven-ii", "--trials", "3", "--max-seconds", "20",
                   "--seed", "4", "--out", str(root), check=True)
    found = [Path(line) for line in result.stdout.split() if line.strip()]
    for session in found:
        align_and_write(session)
    return found


def _train(sessions: list[Path], out: Path, model: str, causal: bool = True, delay_s: float = 0.0,
           clean_up: dict | None = None, **data) -> Path:
    config = DatasetConfig(("emht",), ("pos", "ori", "vel"), **data)
    recipe = {"lr": 1e-2} if model == "mstcn" else {"lr": 3e-3, "batch_size": 1}
    train_run(sessions, config, TrainConfig(model=model, epochs=6, selection="last", causal=causal, delay_s=delay_s,
                                            model_options=TINY[model], **recipe, **(clean_up or {})), out)
    return out


@pytest.fixture(scope="module")
def runs(sessions, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("runs")
    return {name: _train(sessions, root / name, name) for name in TINY}


def _rates(session: Path) -> dict[str, float | None]:
    recorded = Session.open(session)
    return {s: recorded.stream_spec(s).nominal_rate_hz for s in recorded.stream_names}


def _feed_in_random_chunks(feed: LiveFeed, session: Path, seed: int) -> list:
    """Every needed stream's rows, in chunks of 1..60 rows, streams interleaved at random (each in its
    own order); ready() after every chunk."""
    recorded = Session.open(session)
    rng = np.random.default_rng(seed)
    pending = {}
    for stream, columns in feed.spec.streams.items():
        data = recorded.read_columns(stream)
        pending[stream] = (np.asarray(data["t_host_ns"]), np.column_stack([data[c] for c in columns]), [0])
    predictions = []
    while pending:
        stream = list(pending)[rng.integers(len(pending))]
        t, values, at = pending[stream]
        n = int(rng.integers(1, 61))
        feed.add(stream, t[at[0]:at[0] + n], values[at[0]:at[0] + n])
        at[0] += n
        if at[0] >= len(t):
            del pending[stream]
        predictions += feed.ready()
    return predictions


@pytest.mark.parametrize("model", list(TINY))
def test_live_predictions_equal_the_offline_model_frame_for_frame(sessions, runs, model):
    session = sessions[0]
    feed = load_live_model(runs[model], _rates(session))
    assert feed.spec.model == model and feed.spec.rate_hz == 10.0 and feed.spec.classes
    assert set(feed.spec.streams) == {"emht"} and "s1_x_mm" in feed.spec.streams["emht"]
    saved = (runs[model] / "checkpoint.pt").read_bytes()
    assert feed.spec.checkpoint_sha256 == hashlib.sha256(saved).hexdigest() and feed.spec.run_id == model
    live = _feed_in_random_chunks(feed, session, seed=1)
    assert len(live) > 150  # ~20 s at 10 Hz
    times = np.array([p.t_host_ns for p in live])
    assert [p.seq for p in live] == list(range(len(live)))
    assert (np.diff(times) == 100_000_000).all() and times[0] % 100_000_000 == 0  # the 10 Hz grid, no gap
    offline = offline_predictions(session, runs[model], times, _rates(session))
    assert [p.class_index for p in live] == [p.class_index for p in offline]
    assert np.allclose([p.probability for p in live], [p.probability for p in offline], atol=1e-4)
    assert np.ptp([p.probability for p in live]) > 0.02  # the frames' outputs differ: the check means something
    held = _feed_in_random_chunks(load_live_model(runs[model]), session, seed=2)  # no rates: 1 s, both ways
    assert [p.class_index for p in held] == [p.class_index for p in offline_predictions(
        session, runs[model], np.array([p.t_host_ns for p in held]))]


def test_a_delayed_model_labels_each_frame_late_and_the_flush_labels_the_last_ones_as_offline(sessions, tmp_path):
    run = _train(sessions, tmp_path / "delayed", "mstcn", delay_s=1.0)
    session = sessions[1]
    feed = load_live_model(run, _rates(session))
    assert feed.delay == 10  # 1 s at the model's 10 Hz
    streamed = _feed_in_random_chunks(feed, session, seed=3)
    tail = feed.flush()
    assert len(tail) == 10 and feed.flush() == []
    live = streamed + tail
    assert [p.seq for p in live] == list(range(len(live)))  # every frame stepped has its label, in order
    times = np.array([p.t_host_ns for p in live])
    assert (np.diff(times) == 100_000_000).all()
    offline = offline_predictions(session, run, times, _rates(session))
    assert [p.class_index for p in live] == [p.class_index for p in offline]
    assert np.allclose([p.probability for p in live], [p.probability for p in offline], atol=1e-4)
    assert np.ptp([p.probability for p in live]) > 0.02
    # the first second of rows: fewer than 11 frames can be stepped, none is labelled yet; later, a frame is
    # labelled only once the frame 1 s after it has been stepped
    early = load_live_model(run, _rates(session))
    data = Session.open(session).read_columns("emht")
    t, values = np.asarray(data["t_host_ns"]), np.column_stack([data[c] for c in early.spec.streams["emht"]])
    early.add("emht", t[:240], values[:240])
    assert early.ready() == []
    early.add("emht", t[240:720], values[240:720])
    labelled = early.ready()
    assert labelled[0].seq == 0 and len(labelled) > 5
    assert labelled[-1].t_host_ns + 1_000_000_000 + feature_step_ns(10.0) < t[719]


def test_the_decoded_class_is_the_runs_clean_up_decided_lag_frames_late_as_offline(sessions, tmp_path):
    run = _train(sessions, tmp_path / "decoded", "mstcn", delay_s=0.3,
                 clean_up={"min_segment": "1.5", "grammar": "auto", "decode_lag_s": 0.5})
    record = json.loads((run / "run.json").read_text(encoding="utf-8"))
    assert record["decode_lag_frames"] == 5 and record["min_segment_frames"] == 15 and record["switch_scores"]
    session = sessions[2]
    feed = load_live_model(run, _rates(session))
    assert (feed.delay, feed.live.decoding.lag, feed.live.decoding.minimum) == (3, 5, 15)
    streamed = _feed_in_random_chunks(feed, session, seed=5)
    tail = feed.flush()
    assert len(tail) == 3 + 5  # the network's delay, then the decoding's lag, decided as the input ends
    assert feed.flush() == []  # nothing after the end
    live = streamed + tail
    assert [p.seq for p in live] == list(range(len(live))) and all(p.decoded for p in live)
    offline = offline_predictions(session, run, np.array([p.t_host_ns for p in live]), _rates(session))
    assert [p.label for p in live] == [p.label for p in offline]
    assert [p.decoded for p in live] == [p.decoded for p in offline]
    assert np.allclose([p.decoded_probability for p in live], [p.decoded_probability for p in offline], atol=1e-4)
    raw, decoded = [p.label for p in live], [p.decoded for p in live]
    changes = lambda labels: sum(a != b for a, b in zip(labels, labels[1:]))  # noqa: E731
    assert changes(decoded) < changes(raw)  # the decoding merged short segments away: the check means something
    # a frame's decoded class waits for the frame 0.5 s after it: the first frames come only after 5 more
    early = load_live_model(run, _rates(session))
    data = Session.open(session).read_columns("emht")
    t, values = np.asarray(data["t_host_ns"]), np.column_stack([data[c] for c in early.spec.streams["emht"]])
    early.add("emht", t[:720], values[:720])
    first = early.ready()
    assert first and first[-1].t_host_ns + (3 + 5) * 100_000_000 + feature_step_ns(10.0) < t[719]


def test_the_first_frame_waits_for_every_stream_and_drops_are_counted(sessions, runs):
    feed = load_live_model(runs["mstcn"], _rates(sessions[0]))
    data = Session.open(sessions[0]).read_columns("emht")
    t = np.asarray(data["t_host_ns"])
    values = np.column_stack([data[c] for c in feed.spec.streams["emht"]])
    feed.add("emht", t[:240], values[:240])  # the first second
    first = feed.ready()
    step = feature_step_ns(10.0)
    assert first[0].t_host_ns == FrameClock(10.0).time(FrameClock(10.0).first_at_or_after(int(t[0]) + step))
    assert all(p.t_host_ns + step < t[239] for p in first)  # each frame waited for a row after t + s
    assert feed.drop_until(first[-1].t_host_ns + 1_000_000_001) == 10  # 10 frames of 100 ms skipped
    feed.add("emht", t[240:600], values[240:600])
    after = feed.ready()
    assert after[0].t_host_ns == first[-1].t_host_ns + 1_100_000_000
    assert after[0].seq == first[-1].seq + 11  # seq numbers the clock's frames: the skipped ones are a gap


def test_what_cannot_run_live_is_refused_naming_why(sessions, runs, tmp_path):
    with pytest.raises(ConfigError, match="--causal"):
        load_live_model(_train(sessions[:2], tmp_path / "offline", "mstcn", causal=False))
    with pytest.raises(ConfigError, match="--exclude-clutch"):
        load_live_model(_train(sessions[:2], tmp_path / "clutch", "mstcn", exclude_clutch=True))
    with pytest.raises(ConfigError, match="no checkpoint.pt"):
        load_live_model(tmp_path)
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ConfigError, match="junk.pt"):
        load_live_model(tmp_path / "junk.pt")
    saved = torch.load(runs["mstcn"] / "checkpoint.pt", weights_only=True)
    torch.save({**saved, "dataset_config": {**saved["dataset_config"], "normalise": "trial"}}, tmp_path / "trial.pt")
    with pytest.raises(ConfigError, match="--normalise trial"):
        load_live_model(tmp_path / "trial.pt")
    torch.save({**saved, "trials": "hostile"}, tmp_path / "hostile.pt")
    with pytest.raises(ConfigError, match="not a usable gesture run"):
        load_live_model(tmp_path / "hostile.pt")
    for delay in (-3, 2.5, True):  # a delay that is not a whole number of frames >= 0: refused, never run
        torch.save({**saved, "model_config": {**saved["model_config"], "delay": delay}}, tmp_path / "delay.pt")
        with pytest.raises(ConfigError, match="delay"):
            load_live_model(tmp_path / "delay.pt")
    # a decoding that is not one (a damaged or hostile record): refused before a decoder allocates anything
    for field, value, why in (("min_segment_frames", -1, "min_segment_frames"), ("min_segment_frames", 2.5, "min_segment"),
                              ("min_segment_frames", 10**12, "under an hour"), ("decode_lag_frames", 10**9, "under an hour"),
                              ("decode_lag_frames", "5", "decode_lag"), ("switch_scores", [[1.0]], "switch_scores")):
        torch.save({**saved, field: value}, tmp_path / "decoding.pt")
        with pytest.raises(ConfigError, match=why):
            load_live_model(tmp_path / "decoding.pt")
    assert json.loads((runs["mstcn"] / "run.json").read_text())["train_config"]["causal"] is True


@pytest.mark.parametrize("rate", [10.0, 30.0, 29.97, 240.0])
def test_the_frame_clock_finds_the_first_frame_at_or_after_any_host_time(rate):
    clock = FrameClock(rate)
    for t in np.random.default_rng(0).integers(1_700_000_000_000_000_000, 1_800_000_000_000_000_000, 2000).tolist():
        k = clock.first_at_or_after(t)
        assert clock.time(k) >= t > clock.time(k - 1)
    assert FrameClock(30.0).time(3) == 100_000_000 and FrameClock(30.0).time(1) == 33_333_333
