"""Point OBS's recording at the session (folder, MKV container, recognisable file names), and put the
operator's own settings back.

Uses profile parameters (SetProfileParameter), which every obs-websocket v5 has; SetRecordDirectory
only exists from v5.3 (OBS 30), and Debian 12 ships OBS 29 with v5.1. OBS reads these settings when a
recording starts, and saves them in its profile at once (so they outlive an OBS that is killed). The
values midas is about to change are first saved on disk (``saved``), then put back from that copy on
every way out: a normal stop, a lost device, a reconnect to an OBS that was restarted (whose profile
still holds midas's values), and, when midas itself was killed, the next ``midas record`` or
``midas doctor`` (``recover_stale``).
"""

from __future__ import annotations

import logging
from pathlib import Path

from midas_cli.devices.obs.connection import ObsConnection
from midas_cli.devices.obs.saved import SavedSettings, SettingsStore
from midas_cli.errors import DeviceError

log = logging.getLogger(__name__)

# (category, name) per output mode; RecFormat is OBS <= 29, RecFormat2 OBS >= 30 ("mkv" in both)
MODE_KEYS = {
    "Simple": {"folder": ("SimpleOutput", "FilePath"),
               "formats": (("SimpleOutput", "RecFormat"), ("SimpleOutput", "RecFormat2"))},
    "Advanced": {"folder": ("AdvOut", "RecFilePath"),
                 "formats": (("AdvOut", "RecFormat"), ("AdvOut", "RecFormat2"))},
}
FILENAME_KEY = ("Output", "FilenameFormatting")
CONTAINER = "mkv"  # survives a crash (DESIGN.md section 5); MP4 does not
STARTED = "OBS_WEBSOCKET_OUTPUT_STARTED"
STOPPED = "OBS_WEBSOCKET_OUTPUT_STOPPED"
STOP_TIMEOUT_S = 5.0


def segment_file_prefix(device: str, segment: int) -> str:
    """OBS file names of a device's recording segment: ``<device>_s<segment>_<date>_<time>.mkv``."""
    return f"{device}_s{segment}"


class RecordTarget:
    """The profile values that make OBS record into a session's folder."""

    def __init__(self, connection: ObsConnection) -> None:
        self.connection = connection

    def plan(self, folder: Path, file_prefix: str) -> tuple[str, dict[tuple[str, str], str]]:
        """(output mode, the values to set) to record into ``folder`` as ``<file_prefix>_<date>_<time>.mkv``."""
        mode = self.get(("Output", "Mode")) or "Simple"
        if mode not in MODE_KEYS:
            raise DeviceError(f"OBS output mode {mode!r} is unknown (expected Simple or Advanced)")
        if mode == "Advanced" and (self.get(("AdvOut", "RecType")) or "Standard") != "Standard":
            raise DeviceError("OBS records through a custom FFmpeg output: set Settings > Output > Recording > "
                              "Type to Standard so midas can choose the folder and the MKV container")
        keys = MODE_KEYS[mode]
        values = {keys["folder"]: str(folder), **{key: CONTAINER for key in keys["formats"]},
                  FILENAME_KEY: f"{file_prefix}_%CCYY-%MM-%DD_%hh-%mm-%ss"}
        return mode, values

    def current(self, keys: list[tuple[str, str]]) -> list[list[str | None]]:
        """[category, name, value or None] of ``keys`` as OBS has them now."""
        return [[category, name, self.get((category, name))] for category, name in keys]

    def apply(self, values: dict[tuple[str, str], str]) -> None:
        for key, value in values.items():
            self.set(key, value)

    def get(self, key: tuple[str, str]) -> str | None:
        response = self.connection.request("GetProfileParameter", {"parameterCategory": key[0],
                                                                   "parameterName": key[1]})
        return response.get("parameterValue")

    def set(self, key: tuple[str, str], value: str | None) -> None:
        """Set a profile parameter (None deletes it, as it was when unset)."""
        self.connection.request("SetProfileParameter", {"parameterCategory": key[0], "parameterName": key[1],
                                                        "parameterValue": value})


def restore_settings(connection: ObsConnection, saved: SavedSettings) -> list[str]:
    """Put the saved values back into OBS. DeviceError if a profile value cannot be set (the copy must
    then be kept); a scene item that no longer exists is only reported (returned as a warning)."""
    target = RecordTarget(connection)
    for category, name, value in saved.profile:
        target.set((category, name), value)
    warnings = []
    for item in saved.scene_items:
        try:
            connection.request("SetSceneItemEnabled", {"sceneName": item["scene"], "sceneItemId": item["item_id"],
                                                       "sceneItemEnabled": item["enabled"]})
        except DeviceError as exc:
            warnings.append(f"the sync marker's visibility was not put back: {exc}")
    return warnings


def stop_orphan_recording(connection: ObsConnection, folder: str) -> bool:
    """Stop a recording OBS is making into ``folder`` (a killed midas's session); True if it did."""
    if not connection.request("GetRecordStatus").get("outputActive"):
        return False
    current = connection.request("GetRecordDirectory").get("recordDirectory", "")
    if not current or Path(current).resolve() != Path(folder).resolve():
        return False
    connection.request("StopRecord")
    connection.wait_for(STOPPED, STOP_TIMEOUT_S)
    return True


def recover_stale(connection: ObsConnection, store: SettingsStore) -> str | None:
    """If ``store`` holds a copy whose owner is gone (a killed midas), stop the recording it left
    running into its session, put the settings back and delete the copy; the sentence that says so.
    None if there is no copy, or it is this process's own. DeviceError if another running process owns
    it (a second midas using the same OBS), or if the values cannot be set (the copy is kept)."""
    saved = store.load()
    if saved is None:
        return None
    owner = saved.owner()
    if owner == "self":
        return None
    if owner == "alive":
        raise DeviceError(f"OBS at {store.address} is in use by another midas (pid {saved.owner_pid}, since "
                          f"{saved.saved_utc}; its copy of OBS's settings is {store.path}): stop that recording "
                          f"first")
    stopped = stop_orphan_recording(connection, saved.folder)
    warnings = restore_settings(connection, saved)
    store.delete()
    session = Path(saved.folder).parent
    text = (f"OBS at {store.address}: restored the recording settings that a midas killed during a recording "
            f"(pid {saved.owner_pid}, {saved.saved_utc}) had changed: {saved.describe()} (saved copy {store.path}, "
            f"now deleted)")
    if stopped:
        text += (f"; stopped the recording it had left running into {saved.folder} (run `midas session repair "
                 f"{session}`)")
    for warning in warnings:
        text += f"; {warning}"
    return text
