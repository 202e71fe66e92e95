"""Point OBS's recording at the session: folder, MKV container, recognisable file names.

Uses profile parameters (SetProfileParameter), which every obs-websocket v5 has; SetRecordDirectory
only exists from v5.3 (OBS 30), and Debian 12 ships OBS 29 with v5.1. OBS reads these settings when a
recording starts. The previous values are kept and put back when the device closes, so the operator's
own OBS profile is left as it was.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from midas_cli.devices.obs.connection import ObsConnection
from midas_cli.errors import DeviceError

# (category, name) per output mode; RecFormat is OBS <= 29, RecFormat2 OBS >= 30 ("mkv" in both)
MODE_KEYS = {
    "Simple": {"folder": ("SimpleOutput", "FilePath"),
               "formats": (("SimpleOutput", "RecFormat"), ("SimpleOutput", "RecFormat2"))},
    "Advanced": {"folder": ("AdvOut", "RecFilePath"),
                 "formats": (("AdvOut", "RecFormat"), ("AdvOut", "RecFormat2"))},
}
FILENAME_KEY = ("Output", "FilenameFormatting")
CONTAINER = "mkv"  # survives a crash (DESIGN.md section 5); MP4 does not


@dataclass
class RecordTarget:
    """The profile values midas changed, and what they were before (None: not set before)."""

    connection: ObsConnection
    previous: dict[tuple[str, str], str | None] = field(default_factory=dict)

    def point_at(self, folder: Path, file_prefix: str) -> str:
        """Record into ``folder`` as ``<file_prefix>_<date>_<time>.mkv``; return the output mode."""
        mode = self._get(("Output", "Mode")) or "Simple"
        if mode not in MODE_KEYS:
            raise DeviceError(f"OBS output mode {mode!r} is unknown (expected Simple or Advanced)")
        if mode == "Advanced" and (self._get(("AdvOut", "RecType")) or "Standard") != "Standard":
            raise DeviceError("OBS records through a custom FFmpeg output: set Settings > Output > Recording > "
                              "Type to Standard so midas can choose the folder and the MKV container")
        keys = MODE_KEYS[mode]
        self._set(keys["folder"], str(folder))
        for key in keys["formats"]:
            self._set(key, CONTAINER)
        self._set(FILENAME_KEY, f"{file_prefix}_%CCYY-%MM-%DD_%hh-%mm-%ss")
        return mode

    def restore(self) -> None:
        """Put the operator's values back (a deleted value is deleted again)."""
        for (category, name), value in self.previous.items():
            self.connection.request("SetProfileParameter", {"parameterCategory": category, "parameterName": name,
                                                            "parameterValue": value})
        self.previous.clear()

    def _get(self, key: tuple[str, str]) -> str | None:
        response = self.connection.request("GetProfileParameter", {"parameterCategory": key[0],
                                                                   "parameterName": key[1]})
        return response.get("parameterValue")

    def _set(self, key: tuple[str, str], value: str) -> None:
        if key not in self.previous:
            self.previous[key] = self._get(key)
        self.connection.request("SetProfileParameter", {"parameterCategory": key[0], "parameterName": key[1],
                                                        "parameterValue": value})
