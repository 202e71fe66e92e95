"""Issue 23, property-based: a config file (or the rig file it names) that is not a good one is exit 2 with
one short `midas: error:` line, never a traceback, never a hang, never a read until memory runs out.

Hypothesis draws a bad config: a known key with a value of the wrong TOML type; a [slurm] value outside
SLURM's grammar (a shell word, a line break, a NUL, a full-width digit) or out of range; a [record] path
holding a control character; values or tables nested thousands deep; text in another encoding or with
invalid UTF-8 or raw NUL bytes; an unknown key with an odd name; MIDAS_CONFIG naming a device, a FIFO, a
folder or a file over the size cap; or a [record] rig naming a device, FIFO or folder. Each draw runs a
command that reads the config in this process (`midas_cli.commands.main.run`, as `midas` does).

The draws are derandomised (the same on every run); MIDAS_PROPERTY_EXAMPLES raises the count.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from helpers.inprocess import captured

EXAMPLES = int(os.environ.get("MIDAS_PROPERTY_EXAMPLES", "200"))
HANG_S = 30
MAX_LINE = 400  # an error line, whatever the file held
COMMANDS = (["config", "--json"], ["session", "list"], ["rig", "check"])
STR_KEYS = (("record", "rig"), ("record", "sessions"), ("slurm", "partition"), ("slurm", "time"), ("slurm", "mem"),
            ("slurm", "account"), ("slurm", "qos"))
INT_KEYS = (("slurm", "gpus"), ("slurm", "array_parallelism"), ("slurm", "cpus_per_task"))
SLURM_STR = [k for k in STR_KEYS if k[0] == "slurm"]
# never part of a SLURM name, time or size
FORBIDDEN = ("\n", "\r", "\t", " ", ";", "$(id)", "`id`", "\x00", "'", '"', "&", "|", "\uff11", "#", "/", "*", "\\")
GOOD = '[record]\nsessions = "données/über"\n[slurm]\npartition = "gpu"\n'


@dataclass(frozen=True)
class BadConfig:
    """A config file's bytes, or a special file standing for it (``special``), or a good config whose rig
    is a special file (``rig``)."""

    kind: str
    content: bytes = b""
    special: str = ""
    rig: str = ""

    def __repr__(self) -> str:  # hypothesis prints it for a failing draw: keep it short
        return f"BadConfig({self.kind!r}, {self.content[:120]!r}{', ' + self.special if self.special else ''}" \
               f"{', rig ' + self.rig if self.rig else ''})"


def toml_string(text: str) -> str:
    return json.dumps(text)  # JSON's escapes are TOML's (\uXXXX, \n, \", \\)


def entry(section: str, key: str, value: str) -> bytes:
    return f"[{section}]\n{key} = {value}\n".encode()


def nested(depth: int, table: bool) -> str:
    return "{a = " * depth + "1" + "}" * depth if table else "[" * depth + "]" * depth


scalars = {
    "int": st.integers(-10**6, 10**6).map(str),
    "float": st.floats(allow_nan=False, allow_infinity=False).map(repr),
    "bool": st.sampled_from(["true", "false"]),
    "datetime": st.just("1979-05-27T07:32:00Z"),
    "array": st.lists(st.integers(0, 9).map(str), max_size=3).map(lambda v: "[" + ", ".join(v) + "]"),
    "table": st.just("{ a = 1 }"),
    "str": st.text(max_size=12).map(toml_string),
}
word = st.text(alphabet="abcdefghijklmnopqrstuvwxyz0123456789", max_size=6)

wrong_type = st.one_of(
    st.tuples(st.sampled_from(STR_KEYS), st.one_of(*(s for k, s in scalars.items() if k != "str"))),
    st.tuples(st.sampled_from(INT_KEYS), st.one_of(*(s for k, s in scalars.items() if k != "int"))),
).map(lambda kv: BadConfig("wrong-type", entry(*kv[0], kv[1])))

outside_grammar = st.one_of(
    st.tuples(st.sampled_from(SLURM_STR), word, st.sampled_from(FORBIDDEN), word).map(
        lambda t: BadConfig("slurm-grammar", entry(*t[0], toml_string(t[1] + t[2] + t[3])))),
    st.tuples(st.sampled_from(INT_KEYS), st.integers(-10**6, -1)).map(
        lambda t: BadConfig("slurm-range", entry(*t[0], str(t[1])))),
    st.sampled_from(["array_parallelism", "cpus_per_task"]).map(
        lambda key: BadConfig("slurm-range", entry("slurm", key, "0"))),
)

control_in_path = st.tuples(st.sampled_from(["rig", "sessions"]), word, st.sampled_from(
    [chr(c) for c in range(32)] + ["\x7f", ""]), word).map(
    lambda t: BadConfig("path-control", entry("record", t[0], toml_string(t[1] + t[2] + t[3] if t[2] else ""))))

deep = st.one_of(
    st.tuples(st.sampled_from(STR_KEYS + INT_KEYS), st.integers(1, 5000), st.booleans()).map(
        lambda t: BadConfig("deep-value", entry(*t[0], nested(t[1], t[2])))),
    st.integers(2, 3000).map(lambda d: BadConfig("deep-table", ("[" + ".".join(["a"] * d) + "]\n").encode())),
)

encoded = st.one_of(
    st.sampled_from(["latin-1", "cp1252", "utf-16", "utf-32"]).map(
        lambda codec: BadConfig(f"encoding-{codec}", GOOD.encode(codec))),
    st.tuples(st.integers(0, len(GOOD.encode())), st.sampled_from([b"\xff", b"\xc3\x28", b"\xed\xa0\x80", b"\x80"]))
    .map(lambda t: BadConfig("invalid-utf8", GOOD.encode()[:t[0]] + t[1] + GOOD.encode()[t[0]:])),
    st.integers(0, len(GOOD.encode())).map(
        lambda i: BadConfig("raw-nul", GOOD.encode()[:i] + b"\x00" + GOOD.encode()[i:])),
)

odd_names = st.tuples(st.sampled_from(["record", "slurm", "other"]), st.text(min_size=1, max_size=300)).filter(
    lambda t: t[1] not in ("rig", "sessions")).map(
    lambda t: BadConfig("unknown-key", f"[{t[0]}]\n{toml_string(t[1])} = 1\n".encode("utf-8", "surrogatepass")))

special = st.one_of(
    st.sampled_from(["/dev/zero", "/dev/null", "/dev/urandom", "fifo", "folder", "huge", "link-to-zero"]).map(
        lambda s: BadConfig("special-config", special=s)),
    st.sampled_from(["/dev/zero", "/dev/urandom", "fifo", "folder"]).map(lambda s: BadConfig("special-rig", rig=s)),
)

bad_configs = st.one_of(wrong_type, outside_grammar, control_in_path, deep, encoded, odd_names, special)


def run_midas(args: list[str], env: dict[str, str]) -> tuple[int | None, str, str]:
    """``midas ARGS`` in this process with ``env`` set: (exit code or None when it hung, stdout, stderr)."""
    return captured(args, HANG_S, env)


@pytest.fixture(scope="module")
def places(tmp_path_factory) -> dict[str, Path]:
    """The special files a draw may name (made once): a FIFO nobody writes, a folder, a 2-MiB valid TOML
    file, a link to /dev/zero."""
    root = tmp_path_factory.mktemp("property-config")
    os.mkfifo(root / "fifo")
    (root / "folder").mkdir()
    (root / "huge").write_text(GOOD + "# padding\n" * 200_000, encoding="utf-8")
    (root / "link-to-zero").symlink_to("/dev/zero")
    return {name: root / name for name in ("fifo", "folder", "huge", "link-to-zero")}


def config_for(bad: BadConfig, places: dict[str, Path], workspace: Path) -> tuple[Path, str]:
    """The config file to point MIDAS_CONFIG at, and the path the error line must name."""
    if bad.special:
        path = places.get(bad.special, Path(bad.special))
        return path, str(path)
    path = workspace / "config.toml"
    if bad.rig:
        rig = places.get(bad.rig, Path(bad.rig))
        path.write_text(f"[record]\nrig = {toml_string(str(rig))}\n", encoding="utf-8")
        return path, str(rig)
    path.write_bytes(bad.content)
    return path, str(path)


def test_the_good_config_is_read(places, tmp_path):
    path = tmp_path / "config.toml"
    path.write_text(GOOD, encoding="utf-8")
    code, out, err = run_midas(["config", "--json"], {"MIDAS_CONFIG": str(path), "MIDAS_RIG": "", "MIDAS_SESSIONS": ""})
    assert code == 0, err
    assert json.loads(out)["slurm"] == {"partition": "gpu"}


@pytest.mark.parametrize("text", ['[record]\nsessions = "\\u0000"\n', '[slurm]\npartition = "gpu\\ntouch /tmp/INJ"\n',
                                  '[slurm]\nqos = "normal --wrap=id"\n', '[slurm]\ntime = "10\\n"\n'])
def test_the_issues_reproductions_are_refused(tmp_path, text):
    path = tmp_path / "config.toml"
    path.write_text(text, encoding="utf-8")
    code, out, err = run_midas(["config"], {"MIDAS_CONFIG": str(path), "MIDAS_RIG": "", "MIDAS_SESSIONS": ""})
    assert code == 2 and out == "" and err.count("\n") == 1 and err.startswith(f"midas: error: config {path}: ")


@settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(bad=bad_configs, command=st.sampled_from(COMMANDS))
def test_a_bad_config_is_one_usage_error_line(places, tmp_path_factory, bad: BadConfig, command: list[str]) -> None:
    workspace = tmp_path_factory.mktemp("bad-config")
    path, named = config_for(bad, places, workspace)
    args = ["rig", "check"] if bad.rig else command  # only rig check opens the configured rig
    code, out, err = run_midas(args, {"MIDAS_CONFIG": str(path), "MIDAS_RIG": "", "MIDAS_SESSIONS": ""})
    what = f"`midas {' '.join(args)}` with {bad!r}"
    assert code is not None, f"{what} hung for {HANG_S} s"
    assert code == 2, f"{what} exited {code}: {err[-2000:]}"
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("midas: error: "), f"{what} said: {err[-2000:]}"
    assert named in lines[0] and len(lines[0]) <= MAX_LINE + len(named), f"{what} said: {lines[0][:2000]}"
    assert out == "", f"{what} printed a result: {out[:500]}"
