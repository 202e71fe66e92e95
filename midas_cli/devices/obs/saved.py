"""The operator's own OBS settings, saved on disk before midas changes them, until they are put back.

Before midas points OBS's recording at a session it writes the values it is about to change (profile
parameters, the sync marker's visibility) to ``$XDG_STATE_HOME/midas/obs-settings-<host>-<port>.json``
(``~/.local/state/midas/`` by default), atomically and only if no copy exists yet: a reconnect (OBS
restarted, or the connection dropped) must never save midas's own values as "the operator's". The
copy names its owner (the worker process's PID and start time) and is deleted once the values are back
in OBS. A copy whose owner is gone was left by a midas that was killed: the next ``midas record`` (the
obs device's open) or ``midas doctor`` puts the values back and says so.

No password is stored, only the name of the environment variable or the file it came from.
"""

from __future__ import annotations

import json
import os
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from midas_cli.errors import DeviceError
from midas_cli.processes import process_start

FORMAT = 1
PREFIX = "obs-settings-"


def state_dir() -> Path:
    """``$XDG_STATE_HOME/midas`` (an unset or relative XDG_STATE_HOME means ``~/.local/state``)."""
    base = os.environ.get("XDG_STATE_HOME", "")
    root = Path(base) if base and os.path.isabs(base) else Path.home() / ".local" / "state"
    return root / "midas"


@dataclass
class SavedSettings:
    """What OBS had before midas changed it. ``profile``: [category, name, value or None (unset)];
    ``scene_items``: {scene, item_id, enabled}; ``folder``: where midas pointed the recording."""

    obs: str
    owner_pid: int
    owner_start: str
    saved_utc: str
    folder: str
    password_env: str = ""
    password_file: str = ""
    profile: list[list[Any]] = field(default_factory=list)
    scene_items: list[dict[str, Any]] = field(default_factory=list)
    format: int = FORMAT

    @classmethod
    def for_this_process(cls, obs: str, folder: Path, password_env: str, password_file: str = "") -> "SavedSettings":
        pid = os.getpid()
        return cls(obs, pid, process_start(pid) or "", time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                   str(folder), password_env, password_file)

    def owner(self) -> str:
        """"self" (this process saved it), "alive" (another running process did) or "stale"."""
        start = process_start(self.owner_pid)
        if start is None or (start and self.owner_start and start != self.owner_start):
            return "stale"  # gone, or the PID now belongs to a later process
        return "self" if self.owner_pid == os.getpid() else "alive"

    def describe(self) -> str:
        values = ", ".join(f"{c}.{n}={'(unset)' if v is None else v}" for c, n, v in self.profile)
        items = ", ".join(f"scene item {i['item_id']} of {i['scene']!r} {'shown' if i['enabled'] else 'hidden'}"
                          for i in self.scene_items)
        return "; ".join(part for part in (values, items) if part)


class SettingsStore:
    """The saved copy for one OBS (``host:port``) under ``directory`` (default: ``state_dir()``)."""

    def __init__(self, host: str, port: int, directory: Path | None = None, path: Path | None = None) -> None:
        self.address = f"{host}:{port}"
        safe_host = re.sub(r"[^A-Za-z0-9._-]", "_", host)
        self.path = path or (directory or state_dir()) / f"{PREFIX}{safe_host}-{port}.json"

    @classmethod
    def all_copies(cls, directory: Path | None = None) -> list[Path]:
        folder = directory or state_dir()
        return sorted(folder.glob(f"{PREFIX}*.json")) if folder.is_dir() else []

    def load(self) -> SavedSettings | None:
        """The saved copy, None if there is none; DeviceError if it cannot be read (it is left alone)."""
        return load_copy(self.path)

    def save_new(self, saved: SavedSettings) -> bool:
        """Write ``saved`` only if no copy exists (atomic: a complete file or none); False if one does."""
        return self._write(saved, replace=False)

    def replace(self, saved: SavedSettings) -> None:
        """Rewrite this process's own copy (atomic)."""
        self._write(saved, replace=True)

    def delete(self) -> None:
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass

    def _write(self, saved: SavedSettings, replace: bool) -> bool:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            temporary = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
            with open(temporary, "w", encoding="utf-8") as fh:
                json.dump(asdict(saved), fh, indent=1)
                fh.write("\n")
                fh.flush()
                os.fsync(fh.fileno())
            try:
                if replace:
                    os.replace(temporary, self.path)
                else:
                    os.link(temporary, self.path)  # fails if a copy exists: never overwrite one
            except FileExistsError:
                return False
            finally:
                if temporary.exists():
                    temporary.unlink()
            _fsync_dir(self.path.parent)
        except OSError as exc:
            raise DeviceError(f"cannot save OBS's settings to {self.path} before changing them ({exc}): midas "
                              f"only changes OBS's profile when it can put it back; check that folder "
                              f"(XDG_STATE_HOME)") from None
        return True


def load_copy(path: Path) -> SavedSettings | None:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        if data.get("format") != FORMAT:
            raise ValueError(f"format {data.get('format')!r}, expected {FORMAT}")
        return SavedSettings(**data)
    except FileNotFoundError:
        return None
    except (OSError, ValueError, TypeError) as exc:
        raise DeviceError(f"{path} (OBS settings midas saved before a recording) cannot be read ({exc}): "
                          f"put OBS's Settings > Output > Recording path and format back by hand, then delete "
                          f"that file") from None


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
