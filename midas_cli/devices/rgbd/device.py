"""RGB-D cameras recorded as side-by-side stereo video plus a per-frame time stream.

* ``uvc://INDEX?calib=/usr/local/zed/settings/SN12345.conf&fps=30`` -- a ZED Mini (or any ZED) as a
  plain UVC camera: one 2560x720 frame holds the left and right 1280x720 images side by side. Depth is
  not computed while recording (record raw, correct later): ``midas extract handkp`` computes it with
  StereoSGBM from the factory calibration, which is copied into the session's ``calib/<name>.conf``.
* ``zed://?fps=30`` -- the same through the Stereolabs ZED SDK (pyzed), when it is installed.
* ``sim://rgbd?rate=10&distance=600`` -- a synthetic stereo camera (known calibration and geometry)
  showing fingertip markers that follow the simulated surgeon; it also writes the true fingertip
  positions as ``<name>_truth`` so extraction can be checked against ground truth.

Every device writes ``video/<name>_<NNN>.mkv`` (one file per open, NNN from 000; MKV survives a crash)
and the ``<name>`` stream: seq (frame counter across files), t_host_ns (host clock when the frame was
read), t_device_ns (the camera's timestamp where it has one), file (NNN), frame (index in that file).
"""

from __future__ import annotations

import logging
import time
from abc import abstractmethod
from pathlib import Path
from typing import Any

import numpy as np

from midas_cli.devices.base import Device, DeviceContext, DeviceUrl
from midas_cli.devices.rgbd.calibration import StereoCalibration, load_zed_conf
from midas_cli.errors import ConfigError, DeviceError
from midas_cli.session.device_files import device_file, last_recorded_seq
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec

log = logging.getLogger(__name__)

CODECS = {"mjpg": "MJPG", "ffv1": "FFV1"}
SBS_RESOLUTIONS = {2560: "HD", 3840: "FHD", 4416: "2K", 1344: "VGA"}
HANDS = ("left", "right")
KEYPOINTS = ("thumb", "middle")
MAX_SLEEP_S = 0.01


def video_file(name: str, index: int) -> str:
    """Relative path of the device's ``index``-th video file."""
    return f"video/{name}_{index:03d}.mkv"


def calibration_file(name: str) -> str:
    """Relative path of the calibration copy in the session."""
    return f"calib/{name}.conf"


def keypoint_columns() -> list[Column]:
    """x, y, z (mm, camera frame) of thumb and middle fingertip per hand, as in the HandKP stream."""
    return [Column(f"{hand}_{kp}_{a}_mm", "float", "mm", 2, frame="camera") for hand in HANDS for kp in KEYPOINTS
            for a in "xyz"]


class StereoVideoDevice(Device):
    """Base: writes side-by-side frames to MKV and one row per frame; subclasses grab the frames."""

    kind = "handkp"
    extra_params: dict[str, type] = {}
    extra_defaults: dict[str, Any] = {}

    def __init__(self, name: str, url: DeviceUrl, context: DeviceContext) -> None:
        super().__init__(name, url)
        self.params = url.take({"fps": float, "codec": str, "quality": int, **self.extra_params},
                               {"fps": 30.0, "codec": "mjpg", "quality": 95, **self.extra_defaults})
        if self.params["codec"] not in CODECS or not 0 < self.params["fps"] <= 120:
            raise ConfigError(f"{url.raw}: codec must be one of {', '.join(CODECS)} and fps in (0, 120], "
                              f"got codec={self.params['codec']} fps={self.params['fps']}")
        self.clock = context.clock
        self.session_dir = context.session_dir
        self.writer = None
        self.file_index = 0
        self.frames_in_file = 0
        self._seq = 0
        self._last_t = 0

    @property
    def streams(self) -> list[StreamSpec]:
        columns = (SEQ, T_HOST, Column("t_device_ns", "int", "ns", clock="device", description="camera timestamp"),
                   Column("file", "int", "", description="video/<device>_<file>.mkv holds this frame"),
                   Column("frame", "int", "", description="frame index inside that file"))
        return [StreamSpec(self.name, self.name, columns, self.params["fps"],
                           "side-by-side stereo frames (left | right) recorded to video/; one row per frame")]

    def settings(self) -> dict[str, Any]:
        return {**self.params, "video": f"video/{self.name}_NNN.mkv", "calibration": calibration_file(self.name)}

    # -- subclass hooks ---------------------------------------------------------------------------
    @abstractmethod
    def _start(self) -> tuple[StereoCalibration, dict[str, Any]]:
        """Connect to the camera; return its calibration and what is known of it."""

    @abstractmethod
    def _grab(self) -> tuple[np.ndarray, int | None] | None:
        """The next side-by-side BGR frame (H, 2W, 3) and its camera time (ns), or None if none is ready."""

    def _extra_rows(self) -> dict[str, list[tuple]]:
        return {}

    # -- recording --------------------------------------------------------------------------------
    def open(self) -> dict[str, Any]:
        if not self.session_dir:
            raise DeviceError(f"{self.name}: {self.url.scheme}:// records video into a session; use `midas record`")
        calib, info = self._start()
        conf = device_file(self.session_dir, "calib", f"{self.name}.conf")
        if not conf.exists():
            conf.write_text(calib.to_conf(), encoding="utf-8")
        last = last_recorded_seq(self.session_dir, self.name)
        self._seq = 0 if last is None else last + 1
        self.file_index = len(list(Path(self.session_dir, "video").glob(f"{self.name}_*.mkv")))
        self.writer = self._open_writer(calib.size)
        return {**info, "serial": calib.serial, "calibration": calibration_file(self.name),
                "video": video_file(self.name, self.file_index)}

    def _open_writer(self, eye_size: tuple[int, int]):
        import cv2

        path = device_file(self.session_dir, "video", Path(video_file(self.name, self.file_index)).name)
        size = (2 * eye_size[0], eye_size[1])
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*CODECS[self.params["codec"]]), self.params["fps"],
                                 size)
        if not writer.isOpened():
            raise DeviceError(f"{self.name}: OpenCV cannot write {self.params['codec']} video to {path}")
        writer.set(cv2.VIDEOWRITER_PROP_QUALITY, self.params["quality"])
        self.frames_in_file = 0
        self.frame_size = size
        return writer

    def read(self) -> dict[str, list[tuple]]:
        if self.writer is None:
            raise DeviceError(f"{self.name}: read before open")
        grabbed = self._grab()
        if grabbed is None:
            return self._extra_rows()
        image, t_device = grabbed
        t_host = max(self.clock.now_ns(), self._last_t + 1)
        self._last_t = t_host
        if (image.shape[1], image.shape[0]) != self.frame_size:
            raise DeviceError(f"{self.name}: frame of {image.shape[1]}x{image.shape[0]}, expected "
                              f"{self.frame_size[0]}x{self.frame_size[1]} side by side")
        self.writer.write(image)
        row = (self._seq, t_host, t_device, self.file_index, self.frames_in_file)
        self._seq += 1
        self.frames_in_file += 1
        return {self.name: [row], **self._extra_rows()}

    def finish(self) -> dict[str, list[tuple]]:
        self.final_info = {"video": video_file(self.name, self.file_index), "frames_in_file": self.frames_in_file}
        self._release()
        return {}

    def _release(self) -> None:
        if self.writer is not None:
            self.writer.release()
            self.writer = None

    def close(self) -> None:
        self._release()


class UvcStereoDevice(StereoVideoDevice):
    """A ZED camera over UVC (OpenCV V4L2 capture), side-by-side frames, factory calibration file
    (``calib=``, or the only ``SN*.conf`` in /usr/local/zed/settings)."""

    extra_params = {"calib": str, "width": int, "height": int}
    extra_defaults = {"calib": "", "width": 2560, "height": 720}

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        width = self.params["width"]
        if width not in SBS_RESOLUTIONS:
            raise ConfigError(f"{self.url.raw}: width {width} is no ZED side-by-side mode "
                              f"({', '.join(map(str, SBS_RESOLUTIONS))})")
        self.resolution = SBS_RESOLUTIONS[width]
        self.calib = load_zed_conf(self.params["calib"], self.resolution) if self.params["calib"] else None
        try:
            self.index = int(self.url.target.strip("/"))
        except ValueError:
            raise ConfigError(f"{self.url.raw}: expected uvc://INDEX (the /dev/videoINDEX number)") from None
        self.capture = None

    def _start(self) -> tuple[StereoCalibration, dict[str, Any]]:
        import cv2

        capture = cv2.VideoCapture(self.index, cv2.CAP_V4L2)
        if not capture.isOpened():
            raise DeviceError(f"{self.name}: cannot open /dev/video{self.index} (plugged in? permissions: video group)")
        capture.set(cv2.CAP_PROP_FRAME_WIDTH, self.params["width"])
        capture.set(cv2.CAP_PROP_FRAME_HEIGHT, self.params["height"])
        capture.set(cv2.CAP_PROP_FPS, self.params["fps"])
        size = (int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        if size != (self.params["width"], self.params["height"]):
            capture.release()
            raise DeviceError(f"{self.name}: /dev/video{self.index} gives {size[0]}x{size[1]}, not the side-by-side "
                              f"{self.params['width']}x{self.params['height']} of a ZED")
        self.capture = capture
        calib = self.calib or installed_calibration(self.resolution)
        return calib, {"model": "ZED (UVC side-by-side)", "device": f"/dev/video{self.index}",
                            "fps_reported": capture.get(cv2.CAP_PROP_FPS)}

    def _grab(self) -> tuple[np.ndarray, int | None] | None:
        import cv2

        ok, image = self.capture.read()  # blocks until the next frame (1/fps)
        if not ok:
            raise DeviceError(f"{self.name}: /dev/video{self.index} stopped delivering frames")
        msec = self.capture.get(cv2.CAP_PROP_POS_MSEC)
        return image, int(msec * 1e6) if msec > 0 else None

    def _release(self) -> None:
        super()._release()
        if self.capture is not None:
            self.capture.release()
            self.capture = None


class ZedSdkStereoDevice(StereoVideoDevice):
    """A ZED camera through the Stereolabs SDK (pyzed): side-by-side view, image timestamps."""

    extra_params = {"serial": int}
    extra_defaults = {"serial": 0}

    def _start(self) -> tuple[StereoCalibration, dict[str, Any]]:
        sl = import_pyzed()
        init = sl.InitParameters(camera_resolution=sl.RESOLUTION.HD720, camera_fps=int(self.params["fps"]),
                                 depth_mode=sl.DEPTH_MODE.NONE)
        if self.params["serial"]:
            init.set_from_serial_number(self.params["serial"])
        self.camera, self.mat = sl.Camera(), sl.Mat()
        status = self.camera.open(init)
        if status != sl.ERROR_CODE.SUCCESS:
            raise DeviceError(f"{self.name}: the ZED SDK could not open the camera: {status}")
        serial = self.camera.get_camera_information().serial_number
        calib = load_zed_conf(Path(ZED_SETTINGS) / f"SN{serial}.conf", "HD")
        return calib, {"model": "ZED (Stereolabs SDK)", "sdk": sl.Camera.get_sdk_version()}

    def _grab(self) -> tuple[np.ndarray, int | None] | None:
        sl = import_pyzed()
        if self.camera.grab() != sl.ERROR_CODE.SUCCESS:
            raise DeviceError(f"{self.name}: the ZED SDK stopped delivering frames")
        self.camera.retrieve_image(self.mat, sl.VIEW.SIDE_BY_SIDE)
        stamp = self.camera.get_timestamp(sl.TIME_REFERENCE.IMAGE).get_nanoseconds()
        return np.ascontiguousarray(self.mat.get_data()[:, :, :3]), int(stamp)

    def _release(self) -> None:
        super()._release()
        camera = getattr(self, "camera", None)
        if camera is not None:
            camera.close()
            self.camera = None


ZED_SETTINGS = "/usr/local/zed/settings"


def installed_calibration(resolution: str) -> StereoCalibration:
    """The one factory calibration the ZED SDK keeps in /usr/local/zed/settings (a DeviceError otherwise)."""
    found = sorted(Path(ZED_SETTINGS).glob("SN*.conf"))
    if len(found) != 1:
        raise DeviceError(f"no calib= given and {len(found)} calibration files in {ZED_SETTINGS}: give the camera's, "
                          f"calib=/path/to/SN<serial>.conf (Stereolabs serves it by serial number)")
    return load_zed_conf(found[0], resolution)


def import_pyzed():
    """pyzed.sl, or a DeviceError saying what to do without it."""
    try:
        import pyzed.sl as sl
    except ImportError:
        raise DeviceError("zed:// needs the Stereolabs ZED SDK with its Python API (pyzed), which is not installed; "
                          "install it from stereolabs.com, or record the camera as a UVC device: "
                          "uvc://INDEX?calib=/usr/local/zed/settings/SN<serial>.conf") from None
    return sl


class SimStereoDevice(StereoVideoDevice):
    """A synthetic stereo camera over the simulated surgeon's hands: fingertip markers, true positions."""

    extra_params = {"seed": int, "distance": float, "rate": float}
    extra_defaults = {"seed": 0, "distance": 600.0, "rate": 0.0}

    def __init__(self, name: str, url: DeviceUrl, context: DeviceContext) -> None:
        super().__init__(name, url, context)
        if self.params["rate"]:
            self.params["fps"] = self.params["rate"]
        if "seed" not in url.params:
            self.params["seed"] = context.seed
        if not 300 <= self.params["distance"] <= 1500:
            raise ConfigError(f"{url.raw}: distance must be 300..1500 mm, got {self.params['distance']}")
        self.start_ns = context.start_ns
        self.camera = None
        self._k = 0
        self._truth: list[tuple] = []

    @property
    def streams(self) -> list[StreamSpec]:
        truth = (SEQ, T_HOST, *keypoint_columns())
        return super().streams + [StreamSpec(f"{self.name}_truth", self.name, truth, self.params["fps"],
                                             "true fingertip positions rendered in each frame (simulation only)")]

    def _start(self) -> tuple[StereoCalibration, dict[str, Any]]:
        from midas_cli.synthetic.stereo_camera import SyntheticStereoCamera, zed_mini_like_calibration
        from midas_cli.synthetic.surgeon import MotionConfig, SurgeonMotion

        calib = zed_mini_like_calibration()
        self.camera = SyntheticStereoCamera(calib, seed=self.params["seed"])
        self.motion = SurgeonMotion(MotionConfig(seed=self.params["seed"]))
        self._k = max(0, int(np.ceil((self.clock.now_ns() - self.start_ns) * self.params["fps"] / 1e9)))
        return calib, {"model": "midas synthetic stereo camera (ZED-Mini-like)", "simulated": True}

    def true_keypoints(self, t_s: float) -> np.ndarray:
        """(2 hands, 2 keypoints, 3) mm in the camera frame at session time ``t_s``: the surgeon's fingertips,
        moved along the optical axis so the workspace centre is ``distance`` mm away."""
        positions, _ = self.motion.sensor_poses(np.array([t_s]))
        rotation, translation = self.motion.camera_from_transmitter()
        camera = positions[0] @ rotation.T + translation  # (4 sensors, 3)
        camera[:, 2] += self.params["distance"] - self.motion.config.camera_distance_mm
        return camera[np.array([[1, 0], [2, 3]])]  # per hand (thumb, middle): 0-based sensors (1, 0), (2, 3)

    def _grab(self) -> tuple[np.ndarray, int | None] | None:
        due = self.start_ns + int(round(self._k * 1e9 / self.params["fps"]))
        now = self.clock.now_ns()
        if due > now:
            time.sleep(min((due - now) / 1e9, MAX_SLEEP_S))
            return None
        t_s = self._k / self.params["fps"]
        points = self.true_keypoints(t_s)
        image = self.camera.render(points.reshape(4, 3))
        self._truth.append((self._seq, points.reshape(12).tolist()))
        self._k += 1
        return image, int(round(t_s * 1e9))

    def _extra_rows(self) -> dict[str, list[tuple]]:
        if not self._truth:
            return {}
        rows = [(seq, self._last_t, *values) for seq, values in self._truth]
        self._truth.clear()
        return {f"{self.name}_truth": rows}
