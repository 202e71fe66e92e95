"""Defaults a technician sets once: environment variables and ``~/.config/midas/config.toml``.

Precedence, highest first: the command-line flag, the environment variable, the config file, the
built-in default. The config file is found at ``$MIDAS_CONFIG`` (a file path), else
``$XDG_CONFIG_HOME/midas/config.toml``, else ``~/.config/midas/config.toml``; a missing file is an
empty config. Its sections and keys are checked (a typo is an error, not a silently ignored setting)::

    [record]
    rig = "/etc/midas/console-rig.toml"   # MIDAS_RIG; relative paths are relative to this file
    sessions = "/data/midas/sessions"     # MIDAS_SESSIONS; where `midas record` puts new sessions
    priority = "high"                     # the device workers' priority: normal (default) or high (nice -10)

    [slurm]                               # `--executor slurm` settings (flags override them)
    partition = "gpu"
    time = "02:00:00"
    mem = "8G"
    gpus = 0
    array_parallelism = 32

The ``[slurm]`` values are checked against SLURM's own grammar (``slurm_value_problem``) when the file is
read: they become sbatch arguments, so a partition holding a line break or a shell word is refused here.

Only the standard library is imported here, so every command may ask for its defaults at no cost.
"""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path
from typing import Any, Optional

from midas_cli.errors import ConfigError

CONFIG_ENV = "MIDAS_CONFIG"
RIG_ENV = "MIDAS_RIG"
SESSIONS_ENV = "MIDAS_SESSIONS"
DEFAULT_SESSIONS = Path("sessions")
PRIORITY_CHOICES = ("normal", "high")  # `record --priority`, [record] priority (record/priority.py)

# section -> key -> accepted Python types (TOML values); path keys are resolved against the file's folder
KNOWN: dict[str, dict[str, tuple[type, ...]]] = {
    "record": {"rig": (str,), "sessions": (str,), "priority": (str,)},
    "slurm": {"partition": (str,), "time": (str,), "mem": (str,), "gpus": (int,), "array_parallelism": (int,),
              "account": (str,), "qos": (str,), "cpus_per_task": (int,)},
}
PATH_KEYS = {("record", "rig"), ("record", "sessions")}
MAX_TOML_BYTES = 1 << 20  # a config or rig file is a few hundred bytes; /dev/zero is not one
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")

_SLURM_NAME = r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}"  # partition, account and QOS names as slurm.conf/sacctmgr make them
_N = r"[0-9]+"
# key -> (the whole value must match, what was expected); SLURM's formats, ASCII digits only
SLURM_GRAMMAR: dict[str, tuple[re.Pattern[str], str]] = {
    "partition": (re.compile(rf"{_SLURM_NAME}(,{_SLURM_NAME})*"),
                  "a SLURM partition name (letters, digits, '_', '.', '-'; several separated by commas)"),
    "account": (re.compile(_SLURM_NAME), "a SLURM account name (letters, digits, '_', '.', '-')"),
    "qos": (re.compile(_SLURM_NAME), "a SLURM QOS name (letters, digits, '_', '.', '-')"),
    "time": (re.compile(rf"{_N}(:{_N}){{0,2}}|{_N}-{_N}(:{_N}){{0,2}}"),
             "a SLURM time (minutes, minutes:seconds, hours:minutes:seconds, days-hours, days-hours:minutes or "
             "days-hours:minutes:seconds)"),
    "mem": (re.compile(rf"{_N}[KMGTkmgt]?"), "a SLURM memory size (an integer, optionally with K, M, G or T: 4000M, 8G)"),
}
SLURM_MINIMUM = {"gpus": 0, "array_parallelism": 1, "cpus_per_task": 1}


def config_path() -> Path:
    """Where the config file is looked for (it need not exist)."""
    explicit = os.environ.get(CONFIG_ENV)
    if explicit:
        return Path(explicit).expanduser()
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "midas" / "config.toml"


def _read_small_regular(path: Path, what: str) -> bytes:
    """The bytes of ``path``; ConfigError unless it is a regular file of at most MAX_TOML_BYTES (a folder,
    FIFO or device such as /dev/zero is refused without a blocking read). FileNotFoundError passes."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO cannot block the open
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = "a folder" if stat.S_ISDIR(mode) else "not a regular file"
            raise ConfigError(f"{what} {path} is {kind}, expected a TOML file")
        os.set_blocking(fd, True)
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(MAX_TOML_BYTES + 1)
    finally:
        os.close(fd)
    if len(data) > MAX_TOML_BYTES:
        raise ConfigError(f"{what} {path} is larger than {MAX_TOML_BYTES >> 20} MiB: not a {what}")
    return data


def read_toml(path: Path, what: str) -> dict[str, Any]:
    """The TOML document in ``path`` (``what``: "config", "rig file", named in errors). A file that is not
    a small regular file, not UTF-8, not TOML or nested too deeply to parse is a one-line ConfigError;
    FileNotFoundError passes, for the caller to say what a missing file means."""
    import tomllib  # lazily: only commands that ask for defaults pay for it

    try:
        raw = _read_small_regular(path, what)
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise ConfigError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    try:
        return tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{what} {path} is not UTF-8 text (byte {exc.start}); save it as UTF-8") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{what} {path} is not valid TOML: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{what} {path} is nested too deeply to be a {what}") from None


def load_config(path: Optional[Path] = None) -> dict[str, dict[str, Any]]:
    """The config file's checked sections ({} when there is none); a bad file is a one-line ConfigError."""
    path = config_path() if path is None else path
    try:
        data = read_toml(path, "config")
    except FileNotFoundError:
        if os.environ.get(CONFIG_ENV):
            raise ConfigError(f"{CONFIG_ENV}={path}: no such config file") from None
        return {}
    return _checked(data, path)


def _checked(data: dict[str, Any], path: Path) -> dict[str, dict[str, Any]]:
    result: dict[str, dict[str, Any]] = {}
    for section, values in data.items():
        keys = KNOWN.get(section)
        if keys is None or not isinstance(values, dict):
            raise ConfigError(f"config {path}: unknown section {_shown(section, 40)} (known: "
                              f"{', '.join('[' + s + ']' for s in KNOWN)})")
        for key, value in values.items():
            if key not in keys:
                raise ConfigError(f"config {path}: unknown key {_shown(key, 40)} in [{section}] (known: "
                                  f"{', '.join(keys)})")
            if not isinstance(value, keys[key]) or isinstance(value, bool):
                expected = " or ".join(t.__name__ for t in keys[key])
                raise ConfigError(f"config {path}: [{section}] {key} = {_shown(value)} should be a {expected}")
            problem = slurm_value_problem(key, value) if section == "slurm" else None
            if (section, key) == ("record", "priority") and value not in PRIORITY_CHOICES:
                problem = f"is not one of {', '.join(PRIORITY_CHOICES)}"
            if (section, key) in PATH_KEYS and (not isinstance(value, str) or _CONTROL.search(value) or not value):
                problem = "is not a usable path (empty, or a NUL, line break or other control character)"
            if problem:
                raise ConfigError(f"config {path}: [{section}] {key} = {_shown(value)} {problem}")
            if (section, key) in PATH_KEYS:
                value = str((path.parent / Path(str(value)).expanduser()))
            result.setdefault(section, {})[key] = value
    return result


def _shown(value: Any, limit: int = 80) -> str:
    """``repr(value)``, cut to ``limit`` characters (a value in an error line, whatever its size)."""
    try:
        text = repr(value)
    except RecursionError:
        text = f"<{type(value).__name__} nested too deeply>"
    return text if len(text) <= limit else text[:limit] + "..."


def slurm_value_problem(key: str, value: Any) -> Optional[str]:
    """Why ``value`` is not a valid ``[slurm] key`` setting (None: it is): names and sizes in SLURM's own
    grammar, counts within their range."""
    if key in SLURM_GRAMMAR:
        pattern, expected = SLURM_GRAMMAR[key]
        return None if isinstance(value, str) and pattern.fullmatch(value) else f"is not {expected}"
    if key in SLURM_MINIMUM:
        least = SLURM_MINIMUM[key]
        ok = isinstance(value, int) and not isinstance(value, bool) and value >= least
        return None if ok else f"should be an integer >= {least}"
    return None


def section(name: str) -> dict[str, Any]:
    """One section of the config file ({} when absent)."""
    return load_config().get(name, {})


def default_rig() -> Optional[Path]:
    """The rig file to record from when no --rig/--simulate/--device is given: MIDAS_RIG, then [record] rig."""
    return _record_path(RIG_ENV, "rig")


def default_sessions() -> Path:
    """Where new sessions go when --out is not given: MIDAS_SESSIONS, then [record] sessions, then ./sessions."""
    return _record_path(SESSIONS_ENV, "sessions") or DEFAULT_SESSIONS


def _record_path(env: str, key: str) -> Optional[Path]:
    """A path from the environment variable ``env``, else from ``[record] key`` (None: neither sets it)."""
    value = os.environ.get(env)
    if value:
        return Path(value).expanduser()
    configured = section("record").get(key)
    return Path(configured) if configured else None


def default_priority() -> str:
    """The device workers' priority when --priority is not given: [record] priority, else "normal"."""
    return section("record").get("priority", PRIORITY_CHOICES[0])


def describe_defaults() -> dict[str, Any]:
    """Where each default comes from, for `midas doctor`/`midas config`: value and source per setting."""
    file_config = load_config()
    rows: dict[str, Any] = {"config_file": {"path": str(config_path()), "exists": config_path().is_file()}}
    for key, env in (("rig", RIG_ENV), ("sessions", SESSIONS_ENV)):
        if os.environ.get(env):
            rows[key] = {"value": str(Path(os.environ[env]).expanduser()), "source": env}
        elif key in file_config.get("record", {}):
            rows[key] = {"value": file_config["record"][key], "source": f"{config_path()} [record]"}
        else:
            rows[key] = {"value": str(DEFAULT_SESSIONS) if key == "sessions" else None, "source": "built-in"}
    rows["slurm"] = file_config.get("slurm", {})
    return rows
