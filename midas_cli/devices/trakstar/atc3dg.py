"""``atc3dg://?lib=PATH&rate=80&range=36&metric=1``: the trakSTAR through the vendor ATC3DG library (ctypes).

Opening loads the library (``lib=`` or ``$MIDAS_ATC3DG_LIB``, else the platform's usual names),
calls InitializeBIRDSystem, reads the SYSTEM_CONFIGURATION, selects transmitter 0, sets the
measurement rate, maximum range and metric units, and sets every attached sensor to
DOUBLE_POSITION_ANGLES_TIME_Q records, the hemisphere and the AC notch filters. ``read`` calls
GetSynchronousRecord(ALL_SENSORS), which returns once per measurement cycle, and makes one row in the
simulated EmHT's layout: ``seq, t_host_ns, t_device_s`` (the library's record time, seconds), per
sensor x/y/z (mm), azimuth/elevation/roll (deg) and quality (the library's distortion number). A sensor
whose status is not VALID_STATUS gets empty fields and is counted in ``counters.corrupt``.

Struct layouts and enum values follow the vendor header ATC3DG.h (revision 36.0.19.7).
"""

from __future__ import annotations

import ctypes
import logging
import os
from ctypes import c_double, c_int, c_short, c_ulong, c_ushort
from typing import Any

from midas_cli.devices.base import Device, DeviceContext, DeviceUrl
from midas_cli.devices.emht_layout import emht_stream, first_seq, resume_seq
from midas_cli.errors import ConfigError, DeviceError
from midas_cli.session.schema import StreamSpec

log = logging.getLogger(__name__)

LIB_ENV = "MIDAS_ATC3DG_LIB"
DEFAULT_LIBS = ("libATC3DGlib64.so", "libATC3DG.so", "ATC3DG64.DLL", "ATC3DG.DLL")
# enum SYSTEM_PARAMETER_TYPE
SELECT_TRANSMITTER, POWER_LINE_FREQUENCY, AGC_MODE, MEASUREMENT_RATE, MAXIMUM_RANGE, METRIC = range(6)
# enum SENSOR_PARAMETER_TYPE
DATA_FORMAT, ANGLE_ALIGN, HEMISPHERE, FILTER_AC_WIDE_NOTCH, FILTER_AC_NARROW_NOTCH = range(5)
DOUBLE_POSITION_ANGLES_TIME_Q = 26  # enum DATA_FORMAT_TYPE
HEMISPHERES = {"front": 0, "back": 1, "top": 2, "bottom": 3, "left": 4, "right": 5}
ALL_SENSORS = 0xFFFF
VALID_STATUS = 0
SIMPLE_MESSAGE = 0
ERROR_CODE_MASK = 0xFFFF
ERROR_FLAG = 0x80000000
WARNING_FLAG = 0x40000000
MM_PER_INCH = 25.4

PARAMS = {"lib": str, "rate": float, "range": int, "metric": int, "hemisphere": str, "ac_wide": int,
          "ac_narrow": int, "sensors": int}
DEFAULTS = {"lib": "", "rate": 80.0, "range": 36, "metric": 1, "hemisphere": "front", "ac_wide": 1,
            "ac_narrow": 0, "sensors": 4}


class SystemConfiguration(ctypes.Structure):
    """tagSYSTEM_CONFIGURATION."""

    _fields_ = [("measurementRate", c_double), ("powerLineFrequency", c_double), ("maximumRange", c_double),
                ("agcMode", c_int), ("numberBoards", c_int), ("numberSensors", c_int),
                ("numberTransmitters", c_int), ("transmitterIDRunning", c_int), ("metric", c_int)]


class SensorConfiguration(ctypes.Structure):
    """tagSENSOR_CONFIGURATION (ULONG is the platform's unsigned long, as in the header)."""

    _fields_ = [("serialNumber", c_ulong), ("boardNumber", c_ushort), ("channelNumber", c_ushort),
                ("type", c_int), ("attached", c_int)]


class PositionAnglesTimeQ(ctypes.Structure):
    """tagDOUBLE_POSITION_ANGLES_TIME_Q_RECORD: x, y, z, azimuth, elevation, roll, time (s), quality."""

    _fields_ = [("x", c_double), ("y", c_double), ("z", c_double), ("a", c_double), ("e", c_double),
                ("r", c_double), ("time", c_double), ("quality", c_ushort)]


class Atc3dgEmHT(Device):
    """The trakSTAR / driveBAY through ATC3DG (USB), synchronous records of all sensors."""

    kind = "emht"

    def __init__(self, name: str, url: DeviceUrl, context: DeviceContext) -> None:
        super().__init__(name, url)
        self.params = url.take(PARAMS, DEFAULTS)
        self._validate()
        self.context = context
        self.clock = context.clock
        self._resume = resume_seq(context, name)
        self._lib: ctypes.CDLL | None = None
        self._sensor_ids: list[int] = []
        self._records = (PositionAnglesTimeQ * self.params["sensors"])()
        self._next_seq = 0

    def _validate(self) -> None:
        p, raw = self.params, self.url.raw
        if not 0 < p["rate"] <= 1000:
            raise ConfigError(f"{raw}: rate must be in (0, 1000] Hz, got {p['rate']}")
        if p["range"] not in (36, 72, 144):
            raise ConfigError(f"{raw}: range must be 36, 72 or 144 (inches), got {p['range']}")
        if p["hemisphere"] not in HEMISPHERES:
            raise ConfigError(f"{raw}: hemisphere must be one of {', '.join(HEMISPHERES)}, got {p['hemisphere']!r}")
        for key in ("metric", "ac_wide", "ac_narrow"):
            if p[key] not in (0, 1):
                raise ConfigError(f"{raw}: {key} must be 0 or 1, got {p[key]}")
        if not 1 <= p["sensors"] <= 4:
            raise ConfigError(f"{raw}: sensors must be 1..4, got {p['sensors']}")

    @property
    def streams(self) -> list[StreamSpec]:
        return [emht_stream(self.name, self.params["sensors"], self.params["rate"],
                            "6-DoF pose per sensor from the ATC3DG library, one row per measurement cycle")]

    def settings(self) -> dict[str, Any]:
        return {"library": self._library_name(), "data_format": "DOUBLE_POSITION_ANGLES_TIME_Q", **self.params}

    # -- opening ------------------------------------------------------------------------------------
    def open(self) -> dict[str, Any]:
        self._lib = self._load()
        try:
            return self._initialize()
        except DeviceError:
            self.close()
            raise

    def _library_name(self) -> str:
        return self.params["lib"] or os.environ.get(LIB_ENV, "")

    def _load(self) -> ctypes.CDLL:
        names = [self._library_name()] if self._library_name() else list(DEFAULT_LIBS)
        errors = []
        for name in names:
            try:
                lib = ctypes.CDLL(name)
            except OSError as exc:
                errors.append(str(exc))
                continue
            _declare(lib)
            return lib
        raise DeviceError(f"{self.name}: cannot load the ATC3DG library (tried {', '.join(names)}): "
                          f"{'; '.join(errors)}. Install the trakSTAR driver package and give its path with "
                          f"atc3dg://?lib=/path/to/libATC3DG.so or ${LIB_ENV}")

    def _initialize(self) -> dict[str, Any]:
        p = self.params
        self._check(self._lib.InitializeBIRDSystem(), "InitializeBIRDSystem",
                    "is the tracker powered and connected, and is its USB driver/daemon installed and running?")
        system = self._system_configuration()
        self._set_system(SELECT_TRANSMITTER, c_short(0), "SELECT_TRANSMITTER")
        self._set_system(MEASUREMENT_RATE, c_double(p["rate"]), "MEASUREMENT_RATE")
        self._set_system(MAXIMUM_RANGE, c_double(p["range"]), "MAXIMUM_RANGE")
        self._set_system(METRIC, c_int(p["metric"]), "METRIC")
        serials = self._configure_sensors(system.numberSensors)
        system = self._system_configuration()
        if abs(system.measurementRate - p["rate"]) > 0.01:
            raise DeviceError(f"{self.name}: the tracker runs at {system.measurementRate:g} Hz, asked {p['rate']:g} Hz")
        self._next_seq = first_seq(self.context, self.name, p["rate"])
        return {"model": "trakSTAR (ATC3DG)", "serial": ",".join(serials), "sensors_found": system.numberSensors,
                "measurement_rate_hz": system.measurementRate, "maximum_range_in": system.maximumRange}

    def _system_configuration(self) -> SystemConfiguration:
        system = SystemConfiguration()
        self._check(self._lib.GetBIRDSystemConfiguration(ctypes.byref(system)), "GetBIRDSystemConfiguration")
        return system

    def _configure_sensors(self, found: int) -> list[str]:
        p = self.params
        if found < p["sensors"]:
            raise DeviceError(f"{self.name}: the tracker reports {found} sensor port(s), asked for {p['sensors']}")
        serials = []
        for sensor in range(p["sensors"]):
            for param, value, label in ((DATA_FORMAT, c_int(DOUBLE_POSITION_ANGLES_TIME_Q), "DATA_FORMAT"),
                                        (HEMISPHERE, c_int(HEMISPHERES[p["hemisphere"]]), "HEMISPHERE"),
                                        (FILTER_AC_WIDE_NOTCH, c_int(p["ac_wide"]), "FILTER_AC_WIDE_NOTCH"),
                                        (FILTER_AC_NARROW_NOTCH, c_int(p["ac_narrow"]), "FILTER_AC_NARROW_NOTCH")):
                code = self._lib.SetSensorParameter(sensor, param, ctypes.byref(value), ctypes.sizeof(value))
                self._check(code, f"SetSensorParameter(sensor {sensor}, {label})")
            config = SensorConfiguration()
            self._check(self._lib.GetSensorConfiguration(sensor, ctypes.byref(config)), "GetSensorConfiguration")
            serials.append(str(config.serialNumber))
        return serials

    def _set_system(self, param: int, value: ctypes._SimpleCData, label: str) -> None:
        code = self._lib.SetSystemParameter(param, ctypes.byref(value), ctypes.sizeof(value))
        self._check(code, f"SetSystemParameter({label}={value.value})")

    def _check(self, code: int, call: str, hint: str = "") -> None:
        if code & ERROR_CODE_MASK == 0:
            return
        buffer = ctypes.create_string_buffer(256)
        self._lib.GetErrorText(code, buffer, len(buffer), SIMPLE_MESSAGE)
        text = buffer.value.decode("ascii", "replace").strip() or f"error code {code & ERROR_CODE_MASK}"
        raise DeviceError(f"{self.name}: {call} failed: {text}" + (f" ({hint})" if hint else ""))

    # -- reading ------------------------------------------------------------------------------------
    def read(self) -> dict[str, list[tuple]]:
        if self._lib is None:
            raise DeviceError(f"{self.name}: read before open")
        code = self._lib.GetSynchronousRecord(ALL_SENSORS, self._records, ctypes.sizeof(self._records))
        t_host_ns = self.clock.now_ns()
        if code & ERROR_FLAG or not code & WARNING_FLAG:  # warnings (e.g. a saturated sensor) show in its status
            self._check(code, "GetSynchronousRecord")
        values: list[Any] = []
        device_time = None
        scale = 1.0 if self.params["metric"] else MM_PER_INCH
        for sensor, record in enumerate(self._records):
            if self._lib.GetSensorStatus(sensor) != VALID_STATUS:
                self.counters.corrupt += 1
                values += [None] * 7
                continue
            device_time = record.time if device_time is None else device_time
            values += [record.x * scale, record.y * scale, record.z * scale, record.a, record.e, record.r,
                       float(record.quality)]
        seq, self._next_seq = self._next_seq, self._next_seq + 1
        self._resume.next_seq = self._next_seq
        return {self.name: [(seq, t_host_ns, device_time, *values)]}

    def close(self) -> None:
        if self._lib is not None:
            self._lib.CloseBIRDSystem()
            self._lib = None


def _declare(lib: ctypes.CDLL) -> None:
    """Argument and return types of the ATC3DG functions used here (ATC3DG.h)."""
    for name in ("InitializeBIRDSystem", "CloseBIRDSystem"):
        getattr(lib, name).argtypes, getattr(lib, name).restype = [], c_int
    lib.GetBIRDSystemConfiguration.argtypes, lib.GetBIRDSystemConfiguration.restype = [ctypes.c_void_p], c_int
    lib.GetSensorConfiguration.argtypes = [c_ushort, ctypes.c_void_p]
    lib.GetSensorConfiguration.restype = c_int
    lib.SetSystemParameter.argtypes, lib.SetSystemParameter.restype = [c_int, ctypes.c_void_p, c_int], c_int
    lib.SetSensorParameter.argtypes = [c_ushort, c_int, ctypes.c_void_p, c_int]
    lib.SetSensorParameter.restype = c_int
    lib.GetSynchronousRecord.argtypes, lib.GetSynchronousRecord.restype = [c_ushort, ctypes.c_void_p, c_int], c_int
    lib.GetSensorStatus.argtypes, lib.GetSensorStatus.restype = [c_ushort], c_ulong
    lib.GetErrorText.argtypes, lib.GetErrorText.restype = [c_int, ctypes.c_char_p, c_int, c_int], c_int
