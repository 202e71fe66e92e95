"""RGB-D: ZED calibration files, SGBM depth on synthetic stereo with known geometry, record + extract."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from midas_cli.clock import HostClock
from midas_cli.devices.base import DeviceContext, DeviceUrl
from midas_cli.devices.rgbd.calibration import Rectifier, load_zed_conf, parse_zed_conf
from midas_cli.devices.rgbd.device import ZedSdkStereoDevice
from midas_cli.analysis.handkp import handkp_spec
from midas_cli.devices.rgbd.stereo import keypoints_3d
from midas_cli.devices.sim.devices import SimHandKP
from midas_cli.errors import ConfigError, DeviceError
from midas_cli.session.reader import Session
from midas_cli.synthetic.stereo_camera import SyntheticStereoCamera, occluded, project_left, zed_mini_like_calibration
from helpers.cli import midas, record_until

ZED_CONF = """[LEFT_CAM_2K]
fx=1400.1
fy=1400.2
cx=1100.0
cy=620.0
k1=-0.17
k2=0.028
[LEFT_CAM_HD]
fx=700.05
fy=700.1
cx=640.5
cy=352.25
k1=-0.171
k2=0.0281
p1=6.7e-05
p2=-0.00015
k3=0
[RIGHT_CAM_HD]
fx=699.9
fy=700.0
cx=633.5
cy=359.3
k1=-0.172
k2=0.0265
p1=0.00016
p2=1.0e-05
k3=0
[STEREO]
Baseline=62.9
TY=0.026
TZ=0.016
CV_HD=0.0062
RX_HD=-0.0009
RZ_HD=0.00077
[MISC]
Sensor_ID=0
"""


def test_zed_conf_is_parsed_for_the_requested_resolution(tmp_path: Path) -> None:
    path = tmp_path / "SN12345678.conf"
    path.write_text(ZED_CONF)
    calib = load_zed_conf(path, "HD")
    assert calib.serial == "12345678" and calib.size == (1280, 720)
    assert (calib.left.fx, calib.left.cy, calib.right.cx) == (700.05, 352.25, 633.5)
    assert calib.left.dist[:2] == (-0.171, 0.0281)
    assert calib.baseline_mm == 62.9 and calib.rotation_rvec == (-0.0009, 0.0062, 0.00077)
    assert parse_zed_conf(calib.to_conf()) == parse_zed_conf(ZED_CONF)  # written back losslessly
    rectifier = Rectifier(calib)
    assert rectifier.baseline_mm == pytest.approx(np.linalg.norm([62.9, 0.026, 0.016]), rel=1e-3)
    with pytest.raises(ConfigError, match=r"RIGHT_CAM_2K"):
        parse_zed_conf(ZED_CONF, "2K")


@pytest.mark.parametrize("depth_mm", [500.0, 750.0, 1000.0])
def test_sgbm_keypoints_are_within_5_mm_of_the_rendered_truth(depth_mm: float) -> None:
    calib = zed_mini_like_calibration()
    camera = SyntheticStereoCamera(calib, seed=2)
    rng = np.random.default_rng(int(depth_mm))
    points = np.column_stack([rng.uniform(-0.2, 0.2, 6) * depth_mm, rng.uniform(-0.12, 0.12, 6) * depth_mm,
                              depth_mm + rng.uniform(-15, 15, 6)])
    visible = ~occluded(points)
    frame = camera.render(points)
    found = keypoints_3d(Rectifier(calib), frame[:, :1280], frame[:, 1280:], project_left(calib, points[visible]))
    error = np.linalg.norm(found - points[visible], axis=1)
    assert np.isfinite(error).sum() >= 4 and np.nanmax(error) < 5.0, error  # no depth is allowed, wrong depth not


def test_depth_follows_the_markers_not_the_background() -> None:
    calib = zed_mini_like_calibration()
    camera = SyntheticStereoCamera(calib, background_mm=1300.0)
    near = np.array([[0.0, 0.0, 600.0]])
    frame = camera.render(near)
    far_point = np.array([[200.0, 100.0, 1300.0]])  # a background pixel
    pixels = project_left(calib, np.vstack([near, far_point]))
    found = keypoints_3d(Rectifier(calib), frame[:, :1280], frame[:, 1280:], pixels)
    assert found[0, 2] == pytest.approx(600.0, abs=3) and found[1, 2] == pytest.approx(1300.0, abs=15)


def test_zed_sdk_backend_without_pyzed_is_a_clear_device_error(tmp_path: Path) -> None:
    if importlib.util.find_spec("pyzed") is not None:
        pytest.skip("pyzed is installed here")
    device = ZedSdkStereoDevice("cam", DeviceUrl.parse("zed://?fps=30"), DeviceContext(HostClock(0), session_dir=str(tmp_path)))
    with pytest.raises(DeviceError, match="ZED SDK .*pyzed.*uvc://INDEX"):
        device.open()


def test_uvc_refuses_a_mode_that_is_no_zed_side_by_side_and_a_bad_calibration(tmp_path: Path) -> None:
    from midas_cli.devices.registry import describe_device

    with pytest.raises(ConfigError, match="width 1920 is no ZED side-by-side mode"):
        describe_device("cam", "uvc://0?width=1920")
    bad = tmp_path / "SN1.conf"
    bad.write_text("[LEFT_CAM_HD]\nfx=1\n")
    with pytest.raises(ConfigError, match="not a ZED calibration file"):
        describe_device("cam", f"uvc://0?calib={bad}")


def test_handkp_layout_matches_the_simulated_handkp_stream() -> None:
    sim = SimHandKP("handkp", DeviceUrl.parse("sim://handkp"), DeviceContext(HostClock(0), 0)).streams[0]
    assert handkp_spec("handkp", 30.0).column_names == sim.column_names


def test_mediapipe_missing_says_how_to_get_it(tmp_path: Path) -> None:
    if importlib.util.find_spec("mediapipe") is not None:
        pytest.skip("mediapipe is installed here")
    from midas_cli.analysis.handkp import MediaPipeDetector

    with pytest.raises(ConfigError, match="mediapipe==0.10.21 and numpy<2"):
        MediaPipeDetector()


def test_record_simulated_rgbd_then_extract_keypoints_within_5_mm(tmp_path: Path) -> None:
    result = record_until(tmp_path, ["--device", "rgbd=sim://rgbd?rate=8&distance=850", "--subject", "1",
                                     "--task", "rgbd", "--trial", "1", "--no-tui"], {"rgbd": 12, "rgbd_truth": 12})
    assert result.returncode == 0, result.stderr
    path = Path(result.stdout.strip().splitlines()[-1])
    extract = midas("extract", "handkp", str(path), "--detector", "truth", "--json")
    assert extract.returncode == 0, extract.stderr
    summary = json.loads(extract.stdout)
    verify = midas("session", "verify", str(path))
    assert verify.returncode == 0, verify.stdout + verify.stderr
    session = Session.open(path)
    handkp, truth = session.read_stream("handkp"), session.read_stream("rgbd_truth")
    assert summary["frames"] == len(handkp) == len(truth) >= 12 and (path / "video" / "rgbd_000.mkv").is_file()
    columns = [c for c in handkp.columns if c.endswith("_mm")]
    error = np.linalg.norm((handkp[columns].to_numpy() - truth[columns].to_numpy()).reshape(-1, 4, 3), axis=2)
    # typically well under 2 mm; a single keypoint on a disc edge can reach ~5 mm (frames vary with start-up)
    assert np.nanmedian(error) < 2.0 and np.nanmax(error) < 6.0 and np.isfinite(error).mean() > 0.8
    assert truth[columns[2::3]].to_numpy().min() > 700  # the markers really were ~0.85 m away
    assert session.manifest["streams"]["handkp"]["derived_by"]["detector"] == "truth"
    again = midas("extract", "handkp", str(path), "--detector", "truth")
    assert again.returncode == 4 and "use --force" in again.stderr
