"""Tests of the deterministic surgeon model used by the simulated devices (midas_cli.synthetic.surgeon)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import welch

from midas_cli.synthetic.feet import CAMERA_PEDAL, CLUTCH_PEDAL, N_PEDALS
from midas_cli.synthetic.hands import SENSOR_NAMES
from midas_cli.synthetic.surgeon import MotionConfig, SurgeonMotion

EMHT_HZ = 240.0
LEFT_MIDDLE, LEFT_THUMB, RIGHT_THUMB, RIGHT_MIDDLE = range(4)
ADC_THRESHOLD = 200


def _times(start_s: float, stop_s: float, hz: float) -> np.ndarray:
    return start_s + np.arange(int(round((stop_s - start_s) * hz))) / hz


def _all_outputs(motion: SurgeonMotion, t: np.ndarray) -> dict[str, np.ndarray]:
    positions, angles = motion.sensor_poses(t)
    return {
        "positions": positions,
        "angles": angles,
        "aperture": motion.grasper_aperture(t),
        "keypoints": motion.hand_keypoints(t),
        "pressed": motion.pedal_pressed(t),
        "adc": motion.pedal_adc(t),
    }


def _press_intervals(pressed: np.ndarray, t: np.ndarray) -> list[tuple[float, float]]:
    """(first pressed sample time, first released sample time) of each press in a 1-D bool trace."""
    edges = np.diff(pressed.astype(np.int8), prepend=0, append=0)
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(t[a], t[min(b, len(t) - 1)]) for a, b in zip(starts, ends)]


def _run_lengths(mask: np.ndarray) -> np.ndarray:
    """Lengths of the runs of True in a 1-D bool array."""
    edges = np.diff(mask.astype(np.int8), prepend=0, append=0)
    return np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)


@pytest.fixture(scope="module")
def motion() -> SurgeonMotion:
    return SurgeonMotion(MotionConfig(seed=7))


@pytest.fixture(scope="module")
def emht_window(motion: SurgeonMotion) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ten minutes of EmHT at 240 Hz: times, positions, angles."""
    t = _times(0.0, 600.0, EMHT_HZ)
    positions, angles = motion.sensor_poses(t)
    return t, positions, angles


# ---- determinism ---------------------------------------------------------------------------------


def test_same_seed_gives_bit_identical_outputs() -> None:
    t = _times(0.0, 30.0, EMHT_HZ)
    first = _all_outputs(SurgeonMotion(MotionConfig(seed=3)), t)
    second = _all_outputs(SurgeonMotion(MotionConfig(seed=3)), t)
    for name, values in first.items():
        assert values.tobytes() == second[name].tobytes(), name


def test_batches_of_20_ms_equal_one_call() -> None:
    t = _times(57.0, 63.0, EMHT_HZ)  # crosses the boundary between two schedule chunks
    whole = _all_outputs(SurgeonMotion(MotionConfig(seed=5)), t)
    batched_motion = SurgeonMotion(MotionConfig(seed=5))
    batches = [_all_outputs(batched_motion, t[i : i + 5]) for i in range(0, len(t), 5)]  # 5 samples = 20.8 ms
    for name, values in whole.items():
        joined = np.concatenate([batch[name] for batch in batches])
        assert joined.tobytes() == values.tobytes(), name


def test_order_and_history_of_calls_do_not_matter() -> None:
    rng = np.random.default_rng(0)
    t = np.sort(rng.uniform(0.0, 3700.0, 3000))
    reference = _all_outputs(SurgeonMotion(MotionConfig(seed=11)), t)
    late_first = SurgeonMotion(MotionConfig(seed=11))
    _all_outputs(late_first, np.array([3650.0]))  # schedules generated far ahead before anything else
    order = rng.permutation(len(t))
    shuffled = _all_outputs(late_first, t[order])  # unsorted times
    for name, values in reference.items():
        assert shuffled[name].tobytes() == values[order].tobytes(), name


def test_different_seeds_differ() -> None:
    t = _times(0.0, 60.0, 30.0)
    one = _all_outputs(SurgeonMotion(MotionConfig(seed=1)), t)
    other = _all_outputs(SurgeonMotion(MotionConfig(seed=2)), t)
    for name in ("positions", "angles", "aperture", "adc"):
        assert not np.array_equal(one[name], other[name]), name
    assert np.abs(one["positions"] - other["positions"]).mean() > 5.0


# ---- shapes, ranges, input handling -----------------------------------------------------------------


def test_shapes_and_dtypes(motion: SurgeonMotion) -> None:
    t = _times(0.0, 2.0, 100.0)
    out = _all_outputs(motion, t)
    n = len(t)
    assert len(SENSOR_NAMES) == 4
    assert out["positions"].shape == (n, 4, 3) and out["positions"].dtype == np.float64
    assert out["angles"].shape == (n, 4, 3)
    assert out["aperture"].shape == (n, 2)
    assert out["keypoints"].shape == (n, 2, 2, 3)
    assert out["pressed"].shape == (n, N_PEDALS) and out["pressed"].dtype == bool
    assert out["adc"].shape == (n, N_PEDALS) and np.issubdtype(out["adc"].dtype, np.integer)


def test_fewer_pedals_and_empty_input() -> None:
    motion = SurgeonMotion(MotionConfig(seed=0, n_pedals=6))
    t = _times(0.0, 1.0, 50.0)
    assert motion.pedal_pressed(t).shape == (50, 6)
    assert motion.pedal_adc(t).shape == (50, 6)
    empty = np.empty(0)
    assert motion.sensor_poses(empty)[0].shape == (0, 4, 3)
    assert motion.hand_keypoints(empty).shape == (0, 2, 2, 3)
    assert motion.pedal_adc(empty).shape == (0, 6)


@pytest.mark.parametrize("bad", [np.array([-0.1, 1.0]), np.array([np.nan]), np.array([np.inf])])
def test_rejects_invalid_times(motion: SurgeonMotion, bad: np.ndarray) -> None:
    with pytest.raises(ValueError):
        motion.sensor_poses(bad)


def test_invalid_config_is_rejected() -> None:
    with pytest.raises(ValueError):
        MotionConfig(n_pedals=10)
    with pytest.raises(ValueError):
        MotionConfig(seed=-1)


def test_positions_stay_in_the_console_workspace(motion: SurgeonMotion, emht_window) -> None:
    _, positions, _ = emht_window
    centre = np.asarray(motion.config.workspace_centre_mm)
    assert 250.0 < np.linalg.norm(centre) < 450.0
    offsets = positions.reshape(-1, 3) - centre
    assert np.all(np.abs(offsets) < [90.0, 140.0, 90.0])
    low, high = np.percentile(offsets, [1, 99], axis=0)
    assert np.all(np.abs(low) < [75.0, 115.0, 75.0]) and np.all(np.abs(high) < [75.0, 115.0, 75.0])
    assert np.all(high - low > [40.0, 120.0, 40.0])  # the hands actually use the workspace
    left, right = positions[:, [LEFT_MIDDLE, LEFT_THUMB], 1], positions[:, [RIGHT_THUMB, RIGHT_MIDDLE], 1]
    assert np.mean(left.mean(axis=1) < right.mean(axis=1)) > 0.99  # left hand on the left (smaller y)


def test_orientation_ranges_and_smoothness(emht_window) -> None:
    _, _, angles = emht_window
    azimuth, elevation, roll = angles[..., 0], angles[..., 1], angles[..., 2]
    assert np.all((azimuth >= -180.0) & (azimuth < 180.0)) and np.all((roll >= -180.0) & (roll < 180.0))
    assert np.all((elevation >= -90.0) & (elevation <= 90.0))
    unwrapped = np.unwrap(np.radians(angles), axis=0)
    assert np.degrees(np.abs(np.diff(unwrapped, axis=0))).max() < 5.0  # no jumps at 240 Hz
    span = np.degrees(unwrapped.max(axis=0) - unwrapped.min(axis=0))  # (4, 3)
    assert np.all(span > 20.0)  # tens of degrees of wrist motion on every axis


# ---- hand motion ---------------------------------------------------------------------------------


def test_motion_is_smooth_at_240_hz(emht_window) -> None:
    _, positions, _ = emht_window
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=-1)
    assert steps.max() < 3.0


def test_hand_speeds_are_plausible(emht_window) -> None:
    _, positions, _ = emht_window
    for hand in ([LEFT_MIDDLE, LEFT_THUMB], [RIGHT_THUMB, RIGHT_MIDDLE]):
        centre = positions[:, hand].mean(axis=1)
        speed = np.linalg.norm(np.diff(centre, axis=0), axis=-1) * EMHT_HZ
        assert 10.0 < np.median(speed) < 80.0
        assert 60.0 < np.percentile(speed, 95) < 350.0
        assert 0.2 < np.mean(speed > 20.0) < 0.95


def test_hands_are_partly_coordinated(emht_window) -> None:
    _, positions, _ = emht_window
    left = positions[:, [LEFT_MIDDLE, LEFT_THUMB]].mean(axis=1)
    right = positions[:, [RIGHT_THUMB, RIGHT_MIDDLE]].mean(axis=1)
    correlations = [np.corrcoef(left[:, axis], right[:, axis])[0, 1] for axis in range(3)]
    assert max(correlations) > 0.2  # a shared focus moves both hands
    assert min(correlations) < 0.95  # but they are not rigidly coupled


def test_tremor_is_small_and_in_the_physiological_band(emht_window) -> None:
    _, positions, _ = emht_window
    frequencies, power = welch(positions[: int(120 * EMHT_HZ), LEFT_THUMB], fs=EMHT_HZ, nperseg=480, axis=0)
    power = power.sum(axis=1)
    band = (frequencies >= 8.0) & (frequencies <= 12.0)
    above = (frequencies >= 14.0) & (frequencies <= 20.0)
    assert power[band].mean() / power[above].mean() > 500.0  # a tremor peak, not just motion roll-off
    band_rms = np.sqrt(power[band].sum() * (frequencies[1] - frequencies[0]))
    assert 0.05 < band_rms < 0.5


def test_thumb_middle_distance_is_the_aperture_and_varies_with_grasping(motion: SurgeonMotion, emht_window) -> None:
    t, positions, _ = emht_window
    aperture = motion.grasper_aperture(t)
    distances = np.column_stack([
        np.linalg.norm(positions[:, LEFT_THUMB] - positions[:, LEFT_MIDDLE], axis=-1),
        np.linalg.norm(positions[:, RIGHT_THUMB] - positions[:, RIGHT_MIDDLE], axis=-1),
    ])
    np.testing.assert_allclose(distances, aperture, atol=1e-6)
    assert np.all((aperture >= 15.0) & (aperture <= 90.0))
    for hand in range(2):
        assert np.mean(aperture[:, hand] < 28.0) > 0.1  # closed
        assert np.mean(aperture[:, hand] > 58.0) > 0.3  # open
        first_two_minutes = aperture[: int(120 * EMHT_HZ), hand] < 40.0
        closures = np.count_nonzero(np.diff(first_two_minutes.astype(np.int8)) == 1)
        assert 10 <= closures <= 80  # a few grasps per 10 s


def test_sensors_of_a_hand_move_together(emht_window) -> None:
    _, positions, _ = emht_window
    for thumb, middle in ((LEFT_THUMB, LEFT_MIDDLE), (RIGHT_THUMB, RIGHT_MIDDLE)):
        for axis in (0, 2):  # the grip opens mostly along y (and z when the wrist rolls)
            assert np.corrcoef(positions[:, thumb, axis], positions[:, middle, axis])[0, 1] > 0.6
        midpoint = (positions[:, thumb] + positions[:, middle]) / 2
        separation = np.linalg.norm(positions[:, thumb] - positions[:, middle], axis=-1)
        assert np.linalg.norm(np.ptp(midpoint, axis=0)) > 1.5 * separation.max()  # the hand travels further


# ---- pedals --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pedal_window(motion: SurgeonMotion) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Five minutes of the FPS board at 1 kHz: times, ground truth, ADC counts."""
    t = _times(0.0, 300.0, 1000.0)
    return t, motion.pedal_pressed(t), motion.pedal_adc(t)


def test_adc_counts_are_10_bit_and_separable_by_a_threshold(pedal_window) -> None:
    _, pressed, adc = pedal_window
    assert adc.min() >= 0 and adc.max() <= 1023
    assert adc[~pressed].max() < 80
    assert 0 < np.median(adc[~pressed]) < 60
    assert np.std(adc[~pressed]) > 0.5  # rest noise
    held = pressed & np.roll(pressed, 100, axis=0) & np.roll(pressed, -100, axis=0)  # >= 100 ms from an edge
    assert adc[held].min() > 450
    assert 500 < np.median(adc[held]) < 950
    assert np.mean((adc > ADC_THRESHOLD) != pressed) < 0.002  # only bounce slots disagree


def test_press_force_varies_between_presses(motion: SurgeonMotion, pedal_window) -> None:
    t, pressed, adc = pedal_window
    plateaus = [np.median(adc[(t >= a) & (t < b), 3]) for a, b in _press_intervals(pressed[:, 3], t)]
    assert len(plateaus) >= 5
    assert np.ptp(plateaus) > 50


def test_contact_bounce_at_press_edges(motion: SurgeonMotion, pedal_window) -> None:
    t, pressed, _ = pedal_window
    onset_crossings, release_crossings = [], []
    for pedal in (1, 3, CLUTCH_PEDAL, CAMERA_PEDAL):
        for start, end in _press_intervals(pressed[:, pedal], t):
            for edge, crossings in ((start, onset_crossings), (end, release_crossings)):
                fine = _times(edge - 0.015, edge + 0.015, 50_000.0)
                above = motion.pedal_adc(fine)[:, pedal] > ADC_THRESHOLD
                crossings.append(np.count_nonzero(np.diff(above.astype(np.int8))))
                assert np.count_nonzero(np.diff(motion.pedal_pressed(fine)[:, pedal].astype(np.int8))) == 1
    for crossings in (onset_crossings, release_crossings):
        crossings = np.array(crossings)
        assert len(crossings) >= 10
        assert np.all(crossings % 2 == 1) and np.all(crossings <= 7)
        assert np.mean(crossings >= 3) > 0.4  # most edges chatter back and forth
        assert np.any(crossings == 1)  # and some are clean


def test_clutch_and_other_pedal_usage(pedal_window) -> None:
    t, pressed, _ = pedal_window
    in_first_two_minutes = t < 120.0
    clutch = _press_intervals(pressed[in_first_two_minutes, CLUTCH_PEDAL], t[in_first_two_minutes])
    assert len(clutch) >= 2
    durations = {pedal: [b - a for a, b in _press_intervals(pressed[:, pedal], t)] for pedal in range(N_PEDALS)}
    assert 8 <= len(durations[CLUTCH_PEDAL]) <= 16  # every 20-40 s over five minutes
    assert all(0.5 <= d <= 2.01 for d in durations[CLUTCH_PEDAL])
    assert len(durations[3]) >= 8 and max(durations[3]) <= 1.51  # energy: frequent short presses
    assert len(durations[CAMERA_PEDAL]) >= 2
    assert durations[7] == [] and durations[8] == []  # unmapped channels


@pytest.mark.parametrize("seed", range(5))
def test_clutch_is_pressed_within_two_minutes_for_any_seed(seed: int) -> None:
    t = _times(0.0, 120.0, 100.0)
    clutch = SurgeonMotion(MotionConfig(seed=seed)).pedal_pressed(t)[:, CLUTCH_PEDAL]
    assert len(_press_intervals(clutch, t)) >= 2


def test_clutch_recentres_the_hands() -> None:
    motion = SurgeonMotion(MotionConfig(seed=4))
    t = _times(0.0, 1800.0, 100.0)
    clutches = _press_intervals(motion.pedal_pressed(t)[:, CLUTCH_PEDAL], t)
    assert len(clutches) >= 40
    starts, ends = np.array([c[0] for c in clutches]), np.array([c[1] for c in clutches])
    centre = np.asarray(motion.config.workspace_centre_mm)

    def bimanual_offset(times: np.ndarray) -> np.ndarray:
        return np.linalg.norm(motion.sensor_poses(times)[0].mean(axis=1) - centre, axis=-1)

    assert bimanual_offset(ends).mean() < bimanual_offset(starts).mean() - 5.0


# ---- hand keypoints ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def keypoint_window(motion: SurgeonMotion) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Five minutes of HandKP at 30 Hz: times, keypoints, matching EmHT sensor positions."""
    t = _times(0.0, 300.0, 30.0)
    return t, motion.hand_keypoints(t), motion.sensor_poses(t)[0]


def test_keypoint_gaps_are_nan_runs_and_isolated_misses(keypoint_window) -> None:
    _, keypoints, _ = keypoint_window
    missing = np.isnan(keypoints)
    hand_missing = missing.all(axis=(2, 3))
    np.testing.assert_array_equal(missing, np.broadcast_to(hand_missing[:, :, None, None], missing.shape))
    assert not np.any(keypoints[~missing] == 0.0)
    assert not np.array_equal(hand_missing[:, 0], hand_missing[:, 1])  # hands are detected independently
    for hand in range(2):
        runs = _run_lengths(hand_missing[:, hand])
        assert 0.01 < hand_missing[:, hand].mean() < 0.25
        assert np.count_nonzero(runs == 1) >= 20  # isolated single-frame misses (~1.5 %)
        assert 5 <= np.count_nonzero(runs >= 6) <= 40  # occlusions of >= 0.2 s, a few per minute
        assert runs.max() <= 61  # at most ~2 s


def test_keypoints_are_the_sensor_fingertips_seen_by_the_camera(motion: SurgeonMotion, keypoint_window) -> None:
    _, keypoints, sensors = keypoint_window
    rotation, translation = motion.camera_from_transmitter()
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    expected = sensors[:, [[LEFT_THUMB, LEFT_MIDDLE], [RIGHT_THUMB, RIGHT_MIDDLE]]] @ rotation.T + translation
    detected = ~np.isnan(keypoints[..., 0])
    error = np.linalg.norm(keypoints[detected] - expected[detected], axis=-1)
    assert 2.0 < np.sqrt(np.mean(error**2)) < 4.5
    assert error.max() < 20.0
    assert 450.0 < np.median(keypoints[detected][:, 2]) < 750.0  # ~600 mm in front of the camera


def test_camera_transform_can_be_recovered_from_the_data(motion: SurgeonMotion, keypoint_window) -> None:
    _, keypoints, sensors = keypoint_window
    source = sensors[:, [[LEFT_THUMB, LEFT_MIDDLE], [RIGHT_THUMB, RIGHT_MIDDLE]]].reshape(-1, 3)
    target = keypoints.reshape(-1, 3)
    keep = ~np.isnan(target[:, 0])
    source, target = source[keep], target[keep]
    source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
    u, _, vt = np.linalg.svd((source - source_mean).T @ (target - target_mean))
    fitted = (u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt).T  # Kabsch
    rotation, translation = motion.camera_from_transmitter()
    angle = np.degrees(np.arccos(np.clip((np.trace(fitted @ rotation.T) - 1.0) / 2.0, -1.0, 1.0)))
    assert angle < 0.5
    np.testing.assert_allclose(target_mean - fitted @ source_mean, translation, atol=3.0)


# ---- scale -----------------------------------------------------------------------------------------


def test_large_batches_and_long_sessions_run() -> None:
    motion = SurgeonMotion(MotionConfig(seed=9))
    t = 3 * 3600.0 + np.arange(100_000) / EMHT_HZ  # 1e5 samples, three hours into a session
    out = _all_outputs(motion, t)
    assert np.isfinite(out["positions"]).all() and np.isfinite(out["angles"]).all()
    assert np.linalg.norm(np.diff(out["positions"], axis=0), axis=-1).max() < 3.0
