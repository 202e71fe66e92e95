"""`midas simulate dataset`: sessions verify, ground truth holds, labels follow the paper's table, seeds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from midas_cli.analysis.kinematics_schema import kinematics_spec, side_columns
from midas_cli.labels.taxonomy import shipped_taxonomy
from midas_cli.session.labels import read_frame_labels
from midas_cli.session.reader import Session
from midas_cli.simulate import gestures
from midas_cli.simulate.truth import Distortion
from helpers.cli import SHARED_DATA, midas

COMPASS = SHARED_DATA / "compass-suturing-gestures"


def _simulate(out: Path, platform: str, trials: int, seed: int, *extra: str, seconds: int = 30) -> list[Path]:
    result = midas("simulate", "dataset", "--platform", platform, "--trials", str(trials), "--seed", str(seed),
                   "--out", str(out), "--max-seconds", str(seconds), *extra, check=True, timeout=300)
    return [Path(line) for line in result.stdout.split()]


@pytest.fixture(scope="module")
def raven(tmp_path_factory) -> list[Path]:
    return _simulate(tmp_path_factory.mktemp("raven"), "raven-ii", 2, 5, "--jobs", "2")


@pytest.fixture(scope="module")
def davinci(tmp_path_factory) -> Path:
    return _simulate(tmp_path_factory.mktemp("davinci"), "davinci-xi", 1, 3)[0]


def test_sessions_verify_and_hold_the_contracted_streams(raven: list[Path], davinci: Path) -> None:
    assert midas("session", "verify", *map(str, raven), str(davinci)).returncode == 0
    assert Session.open(raven[0]).stream_names == ["video", "emht", "handkp", "fps", "mtm", "psm"]
    assert Session.open(davinci).stream_names == ["video", "emht", "handkp", "fps"]
    mtm = Session.open(raven[0]).read_stream("mtm")
    assert list(mtm.columns) == kinematics_spec("mtm").column_names
    assert set(mtm["clutch"].unique()) <= {0, 1}


def _truth(session: Path) -> dict:
    return json.loads((session / "calib" / "ground_truth.json").read_text())


def _emht_midpoints(session: Session) -> tuple[np.ndarray, np.ndarray]:
    """(t_host_ns (N,), midpoints (N, 2, 3)) of the left (sensors 2+1) and right (3+4) hands."""
    emht = session.read_stream("emht")
    pos = {s: emht[[f"s{s}_{a}_mm" for a in "xyz"]].to_numpy() for s in range(1, 5)}
    return emht["t_host_ns"].to_numpy(), np.stack([(pos[1] + pos[2]) / 2, (pos[3] + pos[4]) / 2], axis=1)


def _mapped_residual(session_path: Path, shift_ms: float, with_distortion: bool = True) -> np.ndarray:
    """|MTM(t - shift) - (R p + t + f(p))| (N, 2) mm at EmHT sample times."""
    session, truth = Session.open(session_path), _truth(session_path)
    t_emht, mid = _emht_midpoints(session)
    rotation, translation = np.array(truth["emht_to_mtm"]["R"]), np.array(truth["emht_to_mtm"]["t_mm"])
    d = truth["distortion"]
    field = Distortion(np.array(d["amplitude_mm"]), np.array(d["centre_mm"]), d["wavelength_mm"])
    mapped = mid @ rotation.T + translation + (field(mid) if with_distortion else 0.0)
    mtm = session.read_stream("mtm")
    query = t_emht - shift_ms * 1e6
    keep = (query > mtm["t_host_ns"].iloc[0] + 1e8) & (query < mtm["t_host_ns"].iloc[-1])
    residual = []
    for hand, side in enumerate(("left", "right")):
        truth_xyz = np.column_stack([np.interp(query[keep], mtm["t_host_ns"], mtm[f"{side}_{a}_mm"]) for a in "xyz"])
        residual.append(np.linalg.norm(mapped[keep, hand] - truth_xyz, axis=1))
    return np.column_stack(residual)


def test_transform_maps_emht_midpoints_onto_mtm_within_noise(raven: list[Path]) -> None:
    latency = _truth(raven[0])["emht_latency_ms"]
    exact = _mapped_residual(raven[0], latency)
    assert np.sqrt((exact ** 2).mean()) < 0.6  # 0.25 mm sensor noise (midpoint) + interpolation
    rigid_only = _mapped_residual(raven[0], latency, with_distortion=False)
    assert 0.3 < np.sqrt((rigid_only ** 2).mean()) < 3.0  # the distortion is there, and bounded
    assert np.sqrt((_mapped_residual(raven[0], 0.0) ** 2).mean()) > np.sqrt((exact ** 2).mean()) + 0.3


def test_latency_shows_as_the_cross_correlation_lag(raven: list[Path]) -> None:
    session = Session.open(raven[1])
    t_emht, mid = _emht_midpoints(session)
    mtm = session.read_stream("mtm")
    grid = np.arange(mtm["t_host_ns"].iloc[50], mtm["t_host_ns"].iloc[-50], 5_000_000)
    reference = np.diff(np.interp(grid, mtm["t_host_ns"], mtm["right_x_mm"]))
    truth = _truth(raven[1])
    mapped_x = (mid[:, 1] @ np.array(truth["emht_to_mtm"]["R"]).T)[:, 0]
    lags = np.arange(-30, 31)  # 5 ms steps
    scores = [np.corrcoef(reference, np.diff(np.interp(grid + lag * 5_000_000, t_emht, mapped_x)))[0, 1] for lag in lags]
    assert abs(lags[int(np.argmax(scores))] * 5 - truth["emht_latency_ms"]) <= 5


def test_grasper_angle_follows_the_emht_sensor_distance(raven: list[Path]) -> None:
    session = Session.open(raven[0])
    emht, mtm = session.read_stream("emht"), session.read_stream("mtm")
    distance = np.linalg.norm(emht[[f"s3_{a}_mm" for a in "xyz"]].to_numpy()
                              - emht[[f"s4_{a}_mm" for a in "xyz"]].to_numpy(), axis=1)
    shifted = mtm["t_host_ns"] + 40_000_000
    angle = np.interp(emht["t_host_ns"], shifted, mtm["right_grasper_deg"])
    expected = np.degrees(2 * np.arcsin(np.clip(distance / 140.0, 0, 1)))
    assert np.median(np.abs(angle - expected)) < 1.0
    assert angle.max() - angle.min() > 30  # the grasp opens and closes


def test_psm_is_frozen_while_the_clutch_is_pressed(raven: list[Path]) -> None:
    frames = [Session.open(p).read_stream("psm") for p in raven]
    clutched = [f[f["clutch"] == 1] for f in frames if (f["clutch"] == 1).sum() > 5]
    if not clutched:
        pytest.skip("no clutch press in these short trials")
    assert np.ptp(clutched[0]["right_x_mm"].to_numpy()[:5]) < 1e-6


def test_labels_cover_every_frame_with_the_platform_taxonomy(raven: list[Path], davinci: Path) -> None:
    labels = read_frame_labels(raven[0])
    video = Session.open(raven[0]).read_stream("video")
    assert (labels.frames == video["seq"].to_numpy()).all()
    assert labels.meta["taxonomy"] == "peg-transfer" and set(labels.classes()) <= set(gestures.PEG_TRANSFER_TABLE)
    assert labels.labels[0] == "Idle" and "S1" in labels.classes()
    assert set(read_frame_labels(davinci).classes()) <= set(gestures.SUTURING_TABLE)


def test_simulated_gestures_are_the_shipped_taxonomies() -> None:
    """One home for a gesture set: the simulation draws over labels' taxonomy, in its order."""
    for model, name in ((gestures.peg_transfer(), "peg-transfer"), (gestures.hernia_suturing(), "hernia-suturing")):
        assert model.taxonomy == shipped_taxonomy(name) and model.name == name
        assert model.labels == tuple(shipped_taxonomy(name).ids) and len(model.mean_s) == len(model.labels)


def test_duration_statistics_follow_the_papers_table() -> None:
    rng = np.random.default_rng(0)
    for taxonomy in (gestures.peg_transfer(), gestures.hernia_suturing()):
        for k, label in enumerate(taxonomy.labels):
            draws = np.array([taxonomy.draw_duration(rng, label) for _ in range(4000)])
            assert abs(draws.mean() - taxonomy.mean_s[k]) < 0.12 * taxonomy.mean_s[k], label


def test_gesture_order_follows_the_transition_structure() -> None:
    rng = np.random.default_rng(1)
    peg = gestures.peg_transfer()
    sequence = [label for label, _ in gestures.sample_segments(rng, peg)]
    assert sequence[0] == "Idle" and sequence[-1] == "Idle" and sequence.count("S7") == gestures.PEGS_PER_TRIAL
    for a, b in zip(sequence[:-1], sequence[1:]):
        assert peg.transitions[peg.index(a), peg.index(b)] > 0, (a, b)
    suturing = gestures.hernia_suturing()
    assert np.allclose(suturing.transitions.sum(axis=1), 1) and np.all(np.diag(suturing.transitions) == 0)
    assert suturing.transitions[suturing.index("G2"), suturing.index("G3")] > 0.9  # target -> push, learned


@pytest.mark.shared_data("compass-suturing-gestures")
def test_packaged_transition_counts_rederive_from_the_compass_folder() -> None:
    assert gestures.derive_transition_counts(COMPASS) == gestures.load_transition_data()["learned_counts"]


def test_davinci_pedal_ground_truth_and_image_features(davinci: Path) -> None:
    import pandas as pd
    gt = pd.read_csv(davinci / "derived" / "pedals_gt.csv")
    assert list(gt.columns) == ["frame", "t_host_ns", "secondary_energy_left", "secondary_energy_right",
                                "primary_energy_left", "primary_energy_right", "clutch", "camera", "arm_swap"]
    assert gt["camera"].sum() > gt["primary_energy_right"].sum() >= gt["secondary_energy_left"].sum() == 0
    fps = Session.open(davinci).read_stream("fps")
    camera = np.interp(gt["t_host_ns"], fps["t_host_ns"], fps["ch6_pressed"]) > 0.5
    assert (camera == gt["camera"].astype(bool)).mean() > 0.95  # FSR channel 6 = camera pedal
    features = np.load(davinci / "derived" / "image_features.npz")
    assert features["features"].shape == (len(gt), 32) and features["features"].dtype == np.float32
    assert "SYNTHETIC" in str(features["note"])


def test_same_seed_same_data_other_seed_other_data(tmp_path: Path) -> None:
    def digests(paths: list[Path]) -> dict:
        return {n: e["sha256"] for n, e in Session.open(paths[0]).manifest["streams"].items()}
    first = digests(_simulate(tmp_path / "a", "davinci-xi", 1, 9, seconds=5))
    again = digests(_simulate(tmp_path / "b", "davinci-xi", 1, 9, seconds=5))
    other = digests(_simulate(tmp_path / "c", "davinci-xi", 1, 10, seconds=5))
    assert first == again and first["emht"] != other["emht"]


def test_bad_options_are_refused_with_exit_2(tmp_path: Path) -> None:
    result = midas("simulate", "dataset", "--platform", "dvrk", "--trials", "1", "--out", str(tmp_path))
    assert result.returncode == 2 and "raven-ii" in result.stderr


def test_kinematics_spec_layout() -> None:
    names = kinematics_spec("psm").column_names
    assert names[:3] == ["seq", "t_host_ns", "t_device_s"] and names[-1] == "clutch"
    assert names[3:14] == side_columns("left") and len(names) == 26


def _drawn(difficulty: str, trial: int, subjects: int = 2, platform: str = "davinci-xi"):  # noqa: ANN202
    from midas_cli.simulate.dataset import trial_configs
    from midas_cli.simulate.trial import draw_trial
    configs = trial_configs(platform, 4, 7, Path("unused"), subjects, max_seconds=120, difficulty=difficulty)
    return draw_trial(configs[trial - 1])


def test_real_difficulty_draws_one_style_per_subject() -> None:
    first, third, second = _drawn("real", 1), _drawn("real", 3), _drawn("real", 2)
    assert first.config.subject == third.config.subject == "1" and second.config.subject == "2"
    assert first.style.to_json() == third.style.to_json() != second.style.to_json()
    assert not np.allclose(first.hands.placement.angles_deg, third.hands.placement.angles_deg)  # per session


def test_real_difficulty_blends_pauses_and_leaves_stretches_unlabelled() -> None:
    trials = [_drawn("real", i, subjects=4) for i in (1, 2, 3, 4)]
    labels = [label for t in trials for label, _, _ in t.segments]
    assert "" in labels  # suturing has no Idle class: pauses are unlabelled
    assert sum(len(t.blank) for t in trials) >= 1
    for t in trials:
        label_bounds = np.array([s[1] for s in t.segments])
        motion_bounds = np.array([s[1] for s in t.hands.segments])
        assert len(label_bounds) == len(motion_bounds) and np.all(np.diff(motion_bounds) > 0)
        assert np.abs(label_bounds - motion_bounds)[1:].mean() > 0.05  # motion does not switch with the label
    frame_s = np.arange(int(trials[0].duration_s * 30)) / 30.0
    from midas_cli.simulate.trial import _frame_labels
    marked = _frame_labels(trials[0], frame_s)
    for begin, end in trials[0].blank:
        assert set(marked[(frame_s >= begin) & (frame_s < end)]) == {""}


def test_easy_difficulty_is_the_uniform_simulator() -> None:
    easy = _drawn("easy", 1, platform="raven-ii")
    assert easy.style is None and easy.hands.placement is None and len(easy.blank) == 0
    assert all(label for label, _, _ in easy.segments) and easy.hands.segments == easy.segments


def test_difficulty_option_is_checked_and_changes_the_data(tmp_path: Path) -> None:
    bad = midas("simulate", "dataset", "--difficulty", "nightmare", "--trials", "1", "--out", str(tmp_path / "x"))
    assert bad.returncode == 2 and "easy" in bad.stderr
    easy = _simulate(tmp_path / "e", "raven-ii", 1, 9, "--difficulty", "easy", seconds=5)[0]
    real = _simulate(tmp_path / "r", "raven-ii", 1, 9, seconds=5)[0]
    truth = _truth(real)
    assert "difficulty" not in _truth(easy) and truth["difficulty"]["level"] == "real"
    assert len(truth["difficulty"]["sensor_placement"]["angles_deg"]) == 4
    assert Session.open(easy).manifest["streams"]["emht"]["sha256"] != Session.open(real).manifest["streams"]["emht"]["sha256"]
