"""One simulated trial -> one v1 session folder with known ground truth.

Streams (layouts of the simulated rig's devices, built through ``describe_device``): ``video`` (30 Hz
frame clock, the reference), ``emht`` (240 Hz, delayed by the ground-truth latency, with noise),
``handkp`` (30 Hz, occlusion gaps as empty fields), ``fps`` (250 Hz, 9 channels); Raven-II also ``mtm``
and ``psm`` (100 Hz robot kinematics, ``kinematics_spec``). Plus ``labels/gestures.csv``,
``calib/ground_truth.json``, ``derived/image_features.npz`` and, on the da Vinci, ``derived/pedals_gt.csv``.
Host times: the session starts at a fixed, seed-independent epoch plus one hour per trial, so a dataset
is byte-for-byte reproducible from its seed.
Difficulty (``TrialConfig.difficulty``, simulate/style.py): ``easy`` moves every subject alike; ``real``
adds the subject's style, pauses, unlabelled stretches, motion that leads or lags its labels and the
session's sensor placement (recorded under ``difficulty`` in ``calib/ground_truth.json``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.signal import lfilter

from midas_cli.analysis.kinematics_schema import kinematics_spec
from midas_cli.clock import HostClock
from midas_cli.devices.registry import describe_device
from midas_cli.geometry import angles_from_matrices, quaternions_from_matrices
from midas_cli.session import artifacts
from midas_cli.session.labels import write_frame_labels
from midas_cli.session.pedals_gt import pedals_gt_path, write_pedals_gt
from midas_cli.session.schema import StreamSpec
from midas_cli.session.writer import SessionMetadata, SessionWriter
from midas_cli.simulate import gestures, style as difficulty_style
from midas_cli.simulate.truth import GroundTruth, psm_positions
from midas_cli.synthetic import trial_pedals
from midas_cli.synthetic.gesture_hands import PAUSE, GestureHands

log = logging.getLogger(__name__)

EPOCH_NS = 1_720_000_000_000_000_000  # 2024-07-03T09:46:40Z: first simulated session start
TASKS = {"raven-ii": "peg-transfer", "davinci-xi": "suturing"}
DEVICE_URLS = {"video": "sim://video?rate=30", "emht": "sim://emht?rate=240&sensors=4",
               "handkp": "sim://handkp?rate=30", "fps": "sim://fps?rate=250&channels=9"}
KINEMATICS_RATE_HZ = 100.0
EMHT_NOISE_MM, EMHT_NOISE_DEG = 0.25, 0.15
KEYPOINT_NOISE_MM = np.array([1.5, 1.5, 2.5])
FEATURE_DIM = 32
CHUNK_ROWS = 20_000
PEDAL_CHANNELS = {"secondary_energy_left": 1, "secondary_energy_right": 2, "primary_energy_left": 3,
                  "primary_energy_right": 4, "clutch": 5, "camera": 6, "arm_swap": 7}


@dataclass(frozen=True)
class TrialConfig:
    platform: str
    trial: int
    subject: str
    seed: int
    out_root: Path
    latency_ms: float = 40.0
    distortion_mm: float = 1.0
    max_seconds: float | None = None
    difficulty: str = difficulty_style.DEFAULT_DIFFICULTY
    emht_drift_ppm: float = 0.0  # the EmHT's host stamps drift against true time (eval sync's validation)


@dataclass
class _Trial:
    """Everything drawn for one trial (times in s since the session start, true clock). ``segments`` are
    the labels ('' = an unlabelled pause), ``blank`` (M, 2) s the stretches left unlabelled."""

    config: TrialConfig
    segments: list[tuple[str, float, float]]
    schedule: dict[int, np.ndarray]
    hands: GestureHands
    truth: GroundTruth
    duration_s: float
    start_ns: int
    blank: np.ndarray
    style: difficulty_style.SubjectStyle | None = None


def draw_trial(config: TrialConfig) -> _Trial:
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, config.trial]))
    model = gestures.gesture_model_for(config.platform)
    easy = difficulty_style.check_difficulty(config.difficulty) == "easy"
    style = None if easy else difficulty_style.subject_style(config.seed, config.subject, len(model.labels))
    limit = config.max_seconds if style is None or config.max_seconds is None else config.max_seconds * style.speed
    drawn = gestures.sample_segments(rng, model, limit)  # real: durations / speed below, so the cut scales
    seed = config.seed * 1000 + config.trial
    start_ns = EPOCH_NS + config.trial * 3_600_000_000_000
    truth = GroundTruth.build(config.distortion_mm, config.latency_ms)
    if style is None:
        bounds = np.concatenate([[0.0], np.cumsum([d for _, d in drawn])])
        segments = [(label, float(bounds[i]), float(bounds[i + 1])) for i, (label, _) in enumerate(drawn)]
        clutches = trial_pedals.clutch_intervals(rng, config.platform, segments)
        schedule = trial_pedals.pedal_schedule(rng, config.platform, clutches, float(bounds[-1]))
        hands = GestureHands(segments, clutches, seed)
        return _Trial(config, segments, schedule, hands, truth, float(bounds[-1]), start_ns, np.zeros((0, 2)))
    hard = difficulty_style.trial_rng(config.seed, config.trial)
    pause_label = gestures.IDLE if gestures.IDLE in model.labels else ""
    parts = difficulty_style.add_pauses(hard, style, drawn, pause_label, PAUSE)
    bounds = np.concatenate([[0.0], np.cumsum([d for _, _, d in parts])])
    moving = difficulty_style.motion_bounds(hard, style, bounds)
    segments = [(label, float(bounds[i]), float(bounds[i + 1])) for i, (label, _, _) in enumerate(parts)]
    motion = [(key, float(moving[i]), float(moving[i + 1])) for i, (_, key, _) in enumerate(parts)]
    clutches = trial_pedals.clutch_intervals(rng, config.platform, motion)
    schedule = trial_pedals.pedal_schedule(rng, config.platform, clutches, float(bounds[-1]))
    hands = GestureHands(motion, clutches, seed, style, difficulty_style.Placement.draw(config.seed, config.trial),
                         {label: k for k, label in enumerate(model.labels)})
    blank = difficulty_style.unlabelled_stretches(hard, style, float(bounds[-1]))
    return _Trial(config, segments, schedule, hands, truth, float(bounds[-1]), start_ns, blank, style)


def write_trial(config: TrialConfig) -> dict[str, Any]:
    """Generate and write one session; returns {path, duration_s, frames, segments}."""
    trial = draw_trial(config)
    specs, devices = _device_specs(config.platform)
    metadata = SessionMetadata(config.subject, TASKS[config.platform], config.trial, config.platform,
                               "simulated by midas simulate dataset", 30.0)
    writer = SessionWriter.create(config.out_root, metadata, HostClock(trial.start_ns - 10**12), devices,
                                  list(specs.values()), _rig(config), start_ns=trial.start_ns)
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, config.trial, 99]))
    frames = _write_video(writer, specs["video"], trial)
    _write_emht(writer, specs["emht"], trial, rng)
    _write_handkp(writer, specs["handkp"], trial, rng)
    _write_fps(writer, specs["fps"], trial)
    if config.platform == "raven-ii":
        _write_kinematics(writer, specs["mtm"], specs["psm"], trial)
    stop_ns = trial.start_ns + int(round(trial.duration_s * 1e9)) + 50_000_000
    writer.finalize("complete", "simulated", stop_ns, {})
    _write_derived(writer.folder, trial, frames)
    return {"path": str(writer.folder), "duration_s": trial.duration_s, "frames": int(len(frames)),
            "segments": len(trial.segments)}


def _device_specs(platform: str) -> tuple[dict[str, StreamSpec], dict[str, dict[str, Any]]]:
    specs, devices = {}, {}
    for name, url in DEVICE_URLS.items():
        device = describe_device(name, url)
        specs[name] = device.streams[0]
        devices[name] = {"kind": device.kind, "url": url, "settings": device.settings(), "streams": [name],
                         "info": {"model": f"midas simulate dataset ({device.kind})", "serial": None}}
    if platform == "raven-ii":
        for name in ("mtm", "psm"):
            specs[name] = kinematics_spec(name, KINEMATICS_RATE_HZ)
        devices["robot"] = {"kind": "raven", "url": "simulated://raven-ii", "streams": ["mtm", "psm"],
                            "settings": {"simulated": True, "rate": KINEMATICS_RATE_HZ},
                            "info": {"model": "simulated Raven-II telemetry", "serial": None}}
    return specs, devices


def _rig(config: TrialConfig) -> dict[str, Any]:
    return {"simulated": True, "generator": "midas simulate dataset", "seed": config.seed,
            "platform": config.platform, "latency_ms": config.latency_ms, "distortion_mm": config.distortion_mm,
            "difficulty": config.difficulty,
            **({"emht_drift_ppm": config.emht_drift_ppm} if config.emht_drift_ppm else {}),
            "notes": ["every stream is synthetic: generated from a gesture-driven hand/foot model",
                      "ground truth: calib/ground_truth.json; gesture labels: labels/gestures.csv",
                      "derived/image_features.npz holds SYNTHETIC image features (no video exists), "
                      "carrying part of the gesture information"]}


def _append(writer: SessionWriter, spec: StreamSpec, columns: list[np.ndarray]) -> None:
    """Append rows given column arrays (ints as int64 arrays, floats with NaN for missing), in chunks."""
    n = len(columns[0])
    for begin in range(0, n, CHUNK_ROWS):
        parts = [c[begin:begin + CHUNK_ROWS].tolist() for c in columns]
        writer.append(spec.name, spec.format_rows(list(zip(*parts))))


def _host_times(trial: _Trial, rate: float, rng: np.random.Generator | None, offset_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(k (N,), t_host_ns (N,)) of a stream sampled at ``rate`` over the trial, with < 1 ms jitter."""
    k = np.arange(int(np.floor(trial.duration_s * rate)), dtype=np.int64)
    jitter = rng.uniform(0, 1e6, len(k)) if rng is not None else np.zeros(len(k))
    return k, trial.start_ns + np.round(k * 1e9 / rate + offset_s * 1e9 + jitter).astype(np.int64)


def _write_video(writer: SessionWriter, spec: StreamSpec, trial: _Trial) -> np.ndarray:
    k, host = _host_times(trial, 30.0, None)
    _append(writer, spec, [k, host, k / 30.0])
    return k


def _write_emht(writer: SessionWriter, spec: StreamSpec, trial: _Trial, rng: np.random.Generator) -> None:
    k, host = _host_times(trial, 240.0, rng)
    since_start_s = (host - trial.start_ns) / 1e9
    # a stamp at t shows the hands at t - latency - drift * t: the offset to the robot grows with time
    lateness_s = trial.truth.emht_latency_ms / 1e3 + trial.config.emht_drift_ppm * 1e-6 * since_start_s
    true_s = np.maximum(since_start_s - lateness_s, 0.0)
    positions, rotations, _ = trial.hands.sensors(true_s)
    positions = positions + rng.normal(0.0, EMHT_NOISE_MM, positions.shape)
    angles = angles_from_matrices(rotations.reshape(-1, 3, 3), wrap=True).reshape(len(k), 4, 3)
    angles = angles + rng.normal(0.0, EMHT_NOISE_DEG, angles.shape)
    quality = np.clip((np.linalg.norm(positions, axis=2) - 250.0) / 1000.0, 0.0, 1.0)
    block = np.concatenate([positions, angles, quality[:, :, None]], axis=2).reshape(len(k), 28)
    device_s = true_s * (1 + 20e-6) + 12.5
    _append(writer, spec, [k, host, device_s, *block.T])


def _write_handkp(writer: SessionWriter, spec: StreamSpec, trial: _Trial, rng: np.random.Generator) -> None:
    k, host = _host_times(trial, 30.0, rng, offset_s=0.004)
    true_s = (host - trial.start_ns) / 1e9
    positions, _, _ = trial.hands.sensors(true_s)
    cam_r, cam_t = trial.hands.rig.camera_from_transmitter()
    keypoints = positions[:, [[1, 0], [2, 3]]] @ cam_r.T + cam_t  # (N, hand, thumb/middle, 3)
    keypoints = keypoints + rng.normal(0.0, 1.0, keypoints.shape) * KEYPOINT_NOISE_MM
    columns: list[np.ndarray] = [k, host, np.round(true_s * 1e9).astype(np.int64) + 987_654_321]
    for hand in range(2):
        occluded = trial_pedals.pressed_at(trial_pedals.random_presses(rng, 3.0, (0.2, 2.0), trial.duration_s), true_s)
        missed = occluded | (rng.random(len(k)) < 0.015)
        values = keypoints[:, hand].reshape(len(k), 6)
        values[missed] = np.nan
        columns += [*values.T, (~missed).astype(np.int64)]
    _append(writer, spec, columns)


def _write_fps(writer: SessionWriter, spec: StreamSpec, trial: _Trial) -> None:
    k, host = _host_times(trial, 250.0, np.random.default_rng([trial.config.seed, trial.config.trial, 5]))
    true_s = (host - trial.start_ns) / 1e9
    adc, pressed = trial_pedals.fps_block(trial.schedule, true_s, trial.config.seed * 1000 + trial.config.trial)
    micros = (np.round(true_s * 1e6).astype(np.int64) + 3_000_000) % (1 << 32)
    _append(writer, spec, [k, host, micros, *adc.T.astype(np.int64), *pressed.T.astype(np.int64)])


def _write_kinematics(writer: SessionWriter, mtm_spec: StreamSpec, psm_spec: StreamSpec, trial: _Trial) -> None:
    k, host = _host_times(trial, KINEMATICS_RATE_HZ, None)
    true_s = k / KINEMATICS_RATE_HZ
    positions, _, states = trial.hands.sensors(true_s)
    clutch = trial_pedals.pressed_at(trial.schedule[trial_pedals.CLUTCH], true_s)
    truth = trial.truth
    arms = {"mtm": [], "psm": []}
    for hand, pair in enumerate(([1, 0], [2, 3])):
        mtm = truth.mtm_position(positions[:, pair].mean(axis=1))
        quaternion = quaternions_from_matrices(truth.rotation @ states[hand].rotation)
        grasper = np.degrees(2.0 * states[hand].half_angle)
        for name, position in (("mtm", mtm), ("psm", psm_positions(mtm, clutch))):
            velocity = np.gradient(position, 1.0 / KINEMATICS_RATE_HZ, axis=0)
            arms[name] += [*position.T, *quaternion.T, *velocity.T, grasper]
    for name, spec in (("mtm", mtm_spec), ("psm", psm_spec)):
        _append(writer, spec, [k, host, true_s, *arms[name], clutch.astype(np.int64)])


def _write_derived(folder: Path, trial: _Trial, frames: np.ndarray) -> None:
    frame_s = frames / 30.0
    labels = _frame_labels(trial, frame_s)
    model = gestures.gesture_model_for(trial.config.platform)
    write_frame_labels(folder, frames, labels, {
        "taxonomy": model.name, "source": "simulated (midas simulate dataset): exact generator labels",
        "classes": list(model.labels)})
    truth = trial.truth.to_json(trial.hands.rig.camera_from_transmitter())
    if trial.style is not None:
        truth["difficulty"] = {"level": trial.config.difficulty, "subject_style": trial.style.to_json(),
                               "sensor_placement": trial.hands.placement.to_json(),
                               "unlabelled_stretches_s": np.round(trial.blank, 3).tolist(),
                               "note": "simulate/style.py: subject style, pauses, unlabelled stretches, placement"}
    artifacts.write_json(folder, "calib/ground_truth.json", truth)
    features = _image_features(trial, labels, model.labels)
    artifacts.write_npz(folder, "derived/image_features.npz", frame=frames.astype(np.int64), features=features,
                        note=np.array("SYNTHETIC image features (no video was rendered): class embedding of the "
                                      "frame's gesture (a random other gesture for 30% of segments) plus AR(1) "
                                      "noise; they carry some but not all gesture information"))
    if trial.config.platform == "davinci-xi":
        write_pedals_gt(pedals_gt_path(folder), _pedals_gt(trial, frames, frame_s), {
            "source": "simulated (midas simulate dataset): the generator's true foot-pedal states",
            "fps_channels": PEDAL_CHANNELS})


def _frame_labels(trial: _Trial, frame_s: np.ndarray) -> np.ndarray:
    starts = np.array([s[1] for s in trial.segments])
    index = np.clip(np.searchsorted(starts, frame_s, side="right") - 1, 0, len(starts) - 1)
    labels = np.array([s[0] for s in trial.segments], dtype=object)[index]
    for begin, end in trial.blank:
        labels[(frame_s >= begin) & (frame_s < end)] = ""
    return labels


def _image_features(trial: _Trial, labels: np.ndarray, classes: tuple[str, ...]) -> np.ndarray:
    """(N, FEATURE_DIM) float32: class embedding (shared by the dataset's trials) of the frame's gesture, or of
    a random gesture for 30% of segments, plus AR(1) noise (coefficient 0.95 per frame, unit variance).
    ``real`` difficulty: each subject's embedding departs from the shared one (what a camera sees differs
    by subject), 40% of segments confused; an unlabelled pause has its own embedding."""
    embedding = np.random.default_rng([trial.config.seed, 4242]).normal(0.0, 1.0, (len(classes) + 1, FEATURE_DIM))
    confusion = 0.3
    if trial.style is not None:
        subject = np.random.default_rng([trial.config.seed, 4244, difficulty_style.subject_key(trial.config.subject)])
        embedding = embedding + 0.8 * subject.normal(0.0, 1.0, embedding.shape)
        confusion = 0.4
    rng = np.random.default_rng([trial.config.seed, trial.config.trial, 4243])
    true_class = np.array([classes.index(label) if label else len(classes) for label, _, _ in trial.segments])
    confused = rng.random(len(true_class)) < confusion
    shown = np.where(confused, rng.integers(0, len(classes), len(true_class)), true_class)
    starts = np.array([s[1] for s in trial.segments])
    segment = np.clip(np.searchsorted(starts, np.arange(len(labels)) / 30.0, side="right") - 1, 0, len(starts) - 1)
    noise = lfilter([np.sqrt(1 - 0.95**2)], [1.0, -0.95], rng.normal(0.0, 1.0, (len(labels), FEATURE_DIM)), axis=0)
    return (embedding[shown[segment]] + 1.2 * noise).astype(np.float32)


def _pedals_gt(trial: _Trial, frames: np.ndarray, frame_s: np.ndarray) -> pd.DataFrame:
    table = {"frame": frames, "t_host_ns": trial.start_ns + np.round(frame_s * 1e9).astype(np.int64)}
    for name, channel in PEDAL_CHANNELS.items():
        table[name] = trial_pedals.pressed_at(trial.schedule[channel], frame_s).astype(np.int64)
    return pd.DataFrame(table)
