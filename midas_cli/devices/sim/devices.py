"""Simulated devices: the same Device interface and worker path as real hardware, no hardware.

Each simulated device produces sample k at host time ``start + k / rate`` (the session start is
shared by all devices, so every stream follows one surgeon-motion timeline), sleeping until it is
due and stamping it with the host clock when it is "read". ``seq`` is k: after an outage the counter
continues from the current time, so the outage shows as a sequence gap exactly as it would on a real
device. Values come from :class:`~midas_cli.synthetic.surgeon.SurgeonMotion` (deterministic with
the seed). Fault injection for tests: ``dropout_at=S&dropout_for=S`` makes the device go silent and
refuse to reopen for that window (seconds after the session start).
"""

from __future__ import annotations

import time
from abc import abstractmethod
from typing import Any

import numpy as np

from midas_cli.devices.base import Device, DeviceContext, DeviceUrl
from midas_cli.devices.emht_layout import emht_stream
from midas_cli.devices.pedals import PedalStateTracker, PedalThresholds, adc_to_volts
from midas_cli.errors import ConfigError, DeviceError
from midas_cli.session.schema import SEQ, T_HOST, Column, StreamSpec
from midas_cli.synthetic.surgeon import MotionConfig, SurgeonMotion

BLOCK_S = 0.25  # values are computed a block ahead, vectorised; each sample is still stamped when read
MAX_SLEEP_S = 0.01
COMMON_PARAMS = {"seed": int, "dropout_at": float, "dropout_for": float}


class PacedSimulator(Device):
    """Base for simulated devices: pacing, sequence numbers, device clock and fault injection."""

    default_rate: float = 30.0
    extra_params: dict[str, type] = {}
    extra_defaults: dict[str, Any] = {}

    def __init__(self, name: str, url: DeviceUrl, context: DeviceContext) -> None:
        super().__init__(name, url)
        allowed = {"rate": float, **COMMON_PARAMS, **self.extra_params}
        defaults = {"rate": self.default_rate, "seed": context.seed, "dropout_at": -1.0, "dropout_for": 0.0,
                    **self.extra_defaults}
        self.params = url.take(allowed, defaults)
        self.rate = self.params["rate"]
        if not 0 < self.rate <= 2000:
            raise ConfigError(f"{url.raw}: rate must be in (0, 2000] Hz, got {self.rate}")
        self.clock = context.clock
        self.start_ns = context.start_ns
        self.motion = SurgeonMotion(MotionConfig(seed=self.params["seed"]))
        self._next_k: int | None = None
        self._block_start = 0
        self._block: list[tuple] = []

    def settings(self) -> dict[str, Any]:
        return {"simulated": True, **self.params}

    def open(self) -> dict[str, Any]:
        if self._in_dropout(self.clock.now_ns()):
            raise DeviceError(f"{self.name}: simulated device unplugged (dropout window)")
        self._next_k = self._index_at(self.clock.now_ns())
        return {"model": f"midas simulated {self.kind}", "serial": f"SIM-{self.kind.upper()}-{self.params['seed']}"}

    def read(self) -> dict[str, list[tuple]]:
        if self._next_k is None:
            raise DeviceError(f"{self.name}: read before open")
        now = self.clock.now_ns()
        due_ns = self._due_ns(self._next_k)
        if due_ns > now:
            time.sleep(min((due_ns - now) / 1e9, MAX_SLEEP_S))
            return {}
        if self._in_dropout(now):
            time.sleep(MAX_SLEEP_S)
            return {}
        rows = []
        while self._due_ns(self._next_k) <= self.clock.now_ns():
            rows.append(self._row(self._next_k))
            self._next_k += 1
        return {self.name: rows}

    def close(self) -> None:
        self._next_k = None

    def _row(self, k: int) -> tuple:
        if not self._block_start <= k < self._block_start + len(self._block):
            count = max(1, int(round(BLOCK_S * self.rate)))
            self._block_start = k
            self._block = self._values(np.arange(k, k + count) / self.rate)
        values = self._block[k - self._block_start]
        return (k, self.clock.now_ns(), *values)

    @abstractmethod
    def _values(self, t: np.ndarray) -> list[tuple]:
        """Row values after (seq, t_host_ns) for sample times ``t`` (s since session start)."""

    def _due_ns(self, k: int) -> int:
        return self.start_ns + int(round(k * 1e9 / self.rate))

    def _index_at(self, host_ns: int) -> int:
        return max(0, int(np.ceil((host_ns - self.start_ns) * self.rate / 1e9)))

    def _in_dropout(self, host_ns: int) -> bool:
        begin = self.params["dropout_at"]
        t = (host_ns - self.start_ns) / 1e9
        return begin >= 0 and begin <= t < begin + self.params["dropout_for"]


class SimEmHT(PacedSimulator):
    """trakSTAR-like: per sensor position (mm, transmitter frame), azimuth/elevation/roll, quality."""

    kind = "emht"
    default_rate = 240.0
    extra_params = {"sensors": int}
    extra_defaults = {"sensors": 4}

    def __init__(self, name: str, url: DeviceUrl, context: DeviceContext) -> None:
        super().__init__(name, url, context)
        if not 1 <= self.params["sensors"] <= 4:
            raise ConfigError(f"{self.url.raw}: sensors must be 1..4, got {self.params['sensors']}")

    @property
    def streams(self) -> list[StreamSpec]:
        return [emht_stream(self.name, self.params["sensors"], self.rate)]

    def _values(self, t: np.ndarray) -> list[tuple]:
        n = self.params["sensors"]
        pos, ori = self.motion.sensor_poses(t)
        quality = np.clip((np.linalg.norm(pos, axis=2) - 250.0) / 1000.0, 0.0, 1.0)
        device_s = t * (1 + 20e-6) + 12.5  # device clock: own epoch, 20 ppm fast
        block = np.concatenate([pos[:, :n], ori[:, :n], quality[:, :n, None]], axis=2)  # (N, n, 7)
        flat = block.reshape(len(t), n * 7)  # (N, n*7): x y z az el roll q, sensor after sensor
        return [(d, *row) for d, row in zip(device_s.tolist(), flat.tolist())]


class SimFPS(PacedSimulator):
    """The FSR pedal board: raw ADC counts per channel plus debounced press states."""

    kind = "fps"
    default_rate = 250.0
    extra_params = {"channels": int, "press_v": float, "release_v": float}
    extra_defaults = {"channels": 9, "press_v": 1.5, "release_v": 1.0}

    def __init__(self, name: str, url: DeviceUrl, context: DeviceContext) -> None:
        super().__init__(name, url, context)
        if not 1 <= self.params["channels"] <= 9:
            raise ConfigError(f"{self.url.raw}: channels must be 1..9, got {self.params['channels']}")
        thresholds = PedalThresholds.uniform(self.params["channels"], self.params["press_v"], self.params["release_v"])
        self.tracker = PedalStateTracker(thresholds)

    @property
    def streams(self) -> list[StreamSpec]:
        n = self.params["channels"]
        columns = [SEQ, T_HOST, Column("t_device_us", "int", "us", clock="device", description="board micros(), wraps at 2^32")]
        columns += [Column(f"ch{c}_adc", "int", "counts", description="10-bit ADC, Vcc 5 V") for c in range(1, n + 1)]
        columns += [Column(f"ch{c}_pressed", "int", "bool", description="press state, thresholds with hysteresis")
                    for c in range(1, n + 1)]
        return [StreamSpec(self.name, self.name, tuple(columns), self.rate, "foot pedal FSR voltages and states")]

    def _values(self, t: np.ndarray) -> list[tuple]:
        adc = self.motion.pedal_adc(t)[:, : self.params["channels"]]
        micros = (np.round(t * 1e6).astype(np.int64) + 3_000_000) % (1 << 32)
        rows = []
        for us, counts in zip(micros.tolist(), adc):
            pressed = self.tracker.update(adc_to_volts(counts)).astype(int)
            rows.append((us, *counts.tolist(), *pressed.tolist()))
        return rows


class SimVideoClock(PacedSimulator):
    """OBS-like frame clock: one row per frame (no video file), seq = frame index."""

    kind = "video"
    default_rate = 30.0

    @property
    def streams(self) -> list[StreamSpec]:
        columns = (SEQ, T_HOST, Column("t_device_s", "float", "s", 6, clock="device", description="recording timecode"))
        return [StreamSpec(self.name, self.name, columns, self.rate, "video frame times (reference clock for align)")]

    def _values(self, t: np.ndarray) -> list[tuple]:
        return [(float(x),) for x in t]


class SimHandKP(PacedSimulator):
    """RGB-D hand keypoints: thumb and middle fingertip per hand in the camera frame; misses are empty."""

    kind = "handkp"
    default_rate = 30.0

    @property
    def streams(self) -> list[StreamSpec]:
        columns = [SEQ, T_HOST, Column("t_device_ns", "int", "ns", clock="device", description="camera timestamp")]
        for hand in ("left", "right"):
            for kp in ("thumb", "middle"):
                columns += [Column(f"{hand}_{kp}_{a}_mm", "float", "mm", 2, frame="camera") for a in "xyz"]
            columns.append(Column(f"{hand}_detected", "int", "bool", description="1 if the hand was detected"))
        return [StreamSpec(self.name, self.name, tuple(columns), self.rate, "hand keypoints from RGB-D")]

    def _values(self, t: np.ndarray) -> list[tuple]:
        kp = self.motion.hand_keypoints(t)  # (N, 2 hands, 2 keypoints, 3)
        cam_ns = np.round(t * 1e9).astype(np.int64) + 987_654_321
        rows = []
        for ns, frame in zip(cam_ns.tolist(), kp):
            values: list[Any] = [ns]
            for hand in frame:
                detected = not np.isnan(hand).any()
                values += hand.reshape(6).tolist() if detected else [float("nan")] * 6
                values.append(int(detected))
            rows.append(tuple(values))
        return rows
