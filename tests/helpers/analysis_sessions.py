"""Small Raven-II-like sessions with known ground truth for the align/calibrate/eval tests.

Written through the session writer following the issue-5 contract: video 30 Hz (the frame clock),
emht 240 Hz (SimEmHT layout, delayed by ``latency_ms`` on the host clock), handkp 30 Hz (camera
frame, occlusion gaps), fps (SimFPS layout, channel 5 = clutch) and mtm/psm 100 Hz
(``kinematics_spec``). MTM hand position = R @ midpoint(thumb, middle sensors) + t; MTM orientation =
R @ R_thumb @ MOUNT; PSM = PSM_SCALE * MTM position + PSM_OFFSET.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from midas_cli.analysis.kinematics_schema import kinematics_spec
from midas_cli.clock import HostClock
from midas_cli.devices.pedals import adc_to_volts
from midas_cli.devices.registry import describe_device
from midas_cli.geometry import matrices_from_angles, quaternions_from_matrices
from midas_cli.record.markers import events_spec
from midas_cli.session.writer import SessionMetadata, SessionWriter
from midas_cli.synthetic.surgeon import MotionConfig, SurgeonMotion

TRUE_R = matrices_from_angles(np.array([[150.0, 10.0, -5.0]]))[0]
TRUE_T = np.array([-250.0, 40.0, 320.0])
MOUNT = matrices_from_angles(np.array([[0.0, 0.0, -90.0]]))[0]
PSM_SCALE, PSM_OFFSET = 0.5, np.array([10.0, -20.0, 5.0])
START_NS = 1_720_000_000_000_000_000
CLUTCH = 4  # 0-based FPS channel of the clutch pedal


def _rows(t_s: np.ndarray, start_ns: int, *columns: np.ndarray) -> list[tuple]:
    """Rows (seq, t_host_ns, *values) with t_host_ns = start + t."""
    host = start_ns + np.round(t_s * 1e9).astype(np.int64)
    values = np.column_stack(columns) if columns else np.zeros((len(t_s), 0))
    return [(k, int(h), *v) for k, (h, v) in enumerate(zip(host.tolist(), values.tolist()))]


def _robot(motion: SurgeonMotion, t: np.ndarray, robot: str) -> np.ndarray:
    """(N, 23) robot columns after t_device_s: per arm xyz, quaternion, velocity, grasper; clutch."""
    pos, ang = motion.sensor_poses(t)
    rot = matrices_from_angles(ang.reshape(-1, 3)).reshape(-1, 4, 3, 3)
    aperture = motion.grasper_aperture(t)
    arms = []
    for hand, (thumb, middle) in enumerate(((1, 0), (2, 3))):
        p = (pos[:, thumb] + pos[:, middle]) / 2 @ TRUE_R.T + TRUE_T
        if robot == "psm":
            p = PSM_SCALE * p + PSM_OFFSET
        quat = quaternions_from_matrices(TRUE_R @ rot[:, thumb] @ MOUNT)
        grasper = np.degrees(2 * np.arcsin(np.clip(aperture[:, hand] / 60.0, -1, 1)))
        arms += [p, quat, np.gradient(p, t, axis=0), grasper[:, None]]
    clutch = motion.pedal_pressed(t)[:, CLUTCH].astype(float)
    return np.column_stack([*arms, clutch])


def raven_session(root: Path, trial: int = 1, duration_s: float = 30.0, latency_ms: float = 40.0,
                  fps_delay_ms: float = 0.0, seed: int = 0, markers: Sequence[tuple[float, str]] = (),
                  dropped_frames: Sequence[int] = ()) -> Path:
    """Write one session; ``fps_delay_ms`` delays the FPS pressed column (a known detection lag).
    ``markers`` (seconds after the start, text) adds an ``events`` stream; ``dropped_frames`` are video
    frames missing from the video stream (as when the recorder missed their stamps)."""
    motion = SurgeonMotion(MotionConfig(seed=seed))
    devices = {k: describe_device(k, f"sim://{k}", seed) for k in ("video", "emht", "handkp", "fps")}
    specs = {k: d.streams[0] for k, d in devices.items()}
    specs.update(mtm=kinematics_spec("mtm"), psm=kinematics_spec("psm"))
    if markers:
        specs["events"] = events_spec()
    writer = SessionWriter.create(root, SessionMetadata("1", "peg-transfer", trial, "raven-ii"), HostClock(0),
                                  {k: {"kind": k} for k in specs}, list(specs.values()), start_ns=START_NS)
    t_video = np.arange(0, duration_s, 1 / 30)
    writer.append("video", specs["video"].format_rows([row for row in _rows(t_video, START_NS, t_video)
                                                       if row[0] not in set(dropped_frames)]))
    if markers:
        writer.append("events", specs["events"].format_rows(
            [(k, START_NS + round(t * 1e9), text, "mark") for k, (t, text) in enumerate(markers)]))
    t_em = np.arange(0, duration_s, 1 / 240)
    em_values = devices["emht"]._values(t_em)  # SimEmHT rows: device time, 4 x (xyz, angles, quality)
    em_rows = [(k, int(START_NS + round((tk + latency_ms / 1e3) * 1e9)), *v)
               for k, (tk, v) in enumerate(zip(t_em.tolist(), em_values))]
    writer.append("emht", specs["emht"].format_rows(em_rows))
    kp_values = devices["handkp"]._values(t_video)
    writer.append("handkp", specs["handkp"].format_rows(
        [(k, int(START_NS + round(tk * 1e9)), *v) for k, (tk, v) in enumerate(zip(t_video.tolist(), kp_values))]))
    writer.append("fps", specs["fps"].format_rows(_fps_rows(motion, duration_s, fps_delay_ms)))
    t_robot = np.arange(0, duration_s, 1 / 100)
    for robot in ("mtm", "psm"):
        writer.append(robot, specs[robot].format_rows(_rows(t_robot, START_NS, t_robot, _robot(motion, t_robot, robot))))
    writer.finalize("complete", "simulated", START_NS + int(duration_s * 1e9), {})
    return writer.folder


def _fps_rows(motion: SurgeonMotion, duration_s: float, delay_ms: float) -> list[tuple]:
    """FPS rows at 250 Hz: ADC counts and pressed states (the clutch's state delayed by ``delay_ms``)."""
    t = np.arange(0, duration_s, 1 / 250)
    adc = motion.pedal_adc(t)
    pressed = (adc_to_volts(motion.pedal_adc(np.clip(t - delay_ms / 1e3, 0, None))) >= 1.5).astype(int)
    micros = np.round(t * 1e6).astype(np.int64)
    return [(k, int(START_NS + round(tk * 1e9)), int(us), *a.tolist(), *p.tolist())
            for k, (tk, us, a, p) in enumerate(zip(t.tolist(), micros.tolist(), adc, pressed))]
