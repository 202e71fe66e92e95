"""Issue 14, property-based: damaged session folders never crash midas, never pass for good, and never
make a command write outside the session or change what was recorded.

Hypothesis draws a damage (a manifest field of the wrong type, a torn, truncated, non-UTF-8 or
garbage stream CSV, a junk binary copy, junk derived/labels/calib files, a symlink out of the session,
a FIFO where a file should be) and a command that reads sessions, applies the damage to a fresh copy
of a small simulated session and runs the command in this process (`midas_cli.commands.main.run`, as
the `midas` entry point does). For every draw:

* the exit code is a documented one (0, 2, 3, 4), never 1 (midas's own bug), and nothing hangs;
* nothing outside the session folder is created, changed or removed;
* what the session already held is unchanged (only `derived/` outputs may be written), except by
  `session repair`, whose job is to change it;
* where the damage makes the input wrong for that command, the exit code is not 0.

The draws are derandomised (the same on every run, so CI is repeatable); MIDAS_PROPERTY_EXAMPLES
raises the count for a longer hunt.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import stat
from dataclasses import dataclass
from pathlib import Path

import pytest

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from helpers.cli import midas
from helpers.inprocess import run_in_process

# SIGALRM is this module's hang detector (run_midas), so the suite's timeout must not use it too: the
# thread method keeps pytest-timeout's guard over the whole module's examples
pytestmark = [pytest.mark.slow, pytest.mark.timeout(900, method="thread")]

EXAMPLES = int(os.environ.get("MIDAS_PROPERTY_EXAMPLES", "300"))
HANG_S = 60  # a command still running after this long on damaged input is hung (a FIFO opened blindly)
STREAMS = ("video", "emht", "handkp", "fps")
# commands that read a session; {s} is the session folder
COMMANDS = {
    "info": ["session", "info", "{s}"],
    "verify": ["session", "verify", "{s}"],
    "repair": ["session", "repair", "{s}"],
    "labels-stats": ["labels", "stats", "{s}"],
    "align": ["align", "{s}"],
    "eval-pedals": ["eval", "pedals", "{s}"],
    "eval-correlation": ["eval", "correlation", "{s}"],
}
WRITERS = {"align", "eval-pedals", "eval-correlation"}  # write outputs under the session's derived/
DOUBTFUL = {"torn-tail", "time-backwards"}  # damage a reader may live with if it says so
# manifest fields every reader relies on: any value of the wrong JSON type must be refused
STRUCTURAL = [("schema_version",), ("session_id",), ("status",), ("metadata",), ("metadata", "trial"),
              ("start",), ("start", "host_ns"), ("devices",), ("streams",)]
STREAM_FIELDS = [(), ("file",), ("columns",), ("samples",), ("sha256",), ("first_t_host_ns",),
                 ("last_t_host_ns",), ("device",)]


@dataclass(frozen=True)
class Damage:
    kind: str
    target: str = ""
    detail: object = None

    def __str__(self) -> str:
        return f"{self.kind}({self.target}{', ' + repr(self.detail) if self.detail is not None else ''})"


# ---------------------------------------------------------------------------------------------- draws

def _wrong_type(value: object) -> list[object]:
    """JSON values of another type than ``value`` (never null, never int<->float, never bool for a bool)."""
    candidates = {"str": "abc", "int": 12345, "list": [1, "x"], "dict": {"x": 1}}
    own = ("dict" if isinstance(value, dict) else "list" if isinstance(value, list)
           else "str" if isinstance(value, str) else "int" if isinstance(value, (int, float)) else "none")
    return [v for k, v in candidates.items() if k != own]


damages = st.one_of(
    st.builds(Damage, st.just("manifest-type"), st.sampled_from([".".join(p) for p in STRUCTURAL]),
              st.integers(0, 2)),
    st.builds(Damage, st.just("stream-field-type"),
              st.tuples(st.sampled_from(STREAMS), st.sampled_from(STREAM_FIELDS)).map(
                  lambda t: ".".join(("streams",) + (t[0],) + t[1])), st.integers(0, 2)),
    st.builds(Damage, st.just("manifest-junk"), st.just("manifest.json"),
              st.sampled_from([b"", b"{", b"[]", b"null", b"\xff\xfe{}", b'{"streams": []}'])),
    st.builds(Damage, st.sampled_from(["cell-junk", "cell-overflow", "non-utf8", "time-backwards", "torn-tail",
                                       "garbage-line", "fifo", "missing", "directory", "symlink-out",
                                       "npy-junk"]),
              st.sampled_from(STREAMS), st.integers(0, 10_000)),
    st.builds(Damage, st.just("junk-file"),
              st.sampled_from(["labels/gestures.csv", "labels/gestures.json", "derived/pedals_gt.csv",
                               "derived/pedals_gt.json", "calib/ground_truth.json", "derived/aligned.npz"]),
              st.sampled_from([b"", b"\x00\x01garbage\xff", b"a,b\n1,2\n", b"{}", b"PK\x03\x04junk"])),
    st.builds(Damage, st.sampled_from(["derived-symlink-out", "derived-fifo"]), st.just("derived")),
)


# ------------------------------------------------------------------------------------------- applying

def _rewrite_manifest(session: Path, path: tuple[str, ...], pick: int) -> bool:
    manifest = json.loads((session / "manifest.json").read_text())
    node = manifest
    for key in path[:-1]:
        node = node[key]
    options = _wrong_type(node[path[-1]])
    node[path[-1]] = options[pick % len(options)]
    (session / "manifest.json").write_text(json.dumps(manifest))
    return True


def _lines(path: Path) -> list[bytes]:
    return path.read_bytes().splitlines(keepends=True)


def apply(damage: Damage, session: Path, outside: Path) -> bool:
    """Damage ``session``; True if the damage makes the recorded data wrong for every reader."""
    kind, target, detail = damage.kind, damage.target, damage.detail
    if kind in ("manifest-type", "stream-field-type"):
        return _rewrite_manifest(session, tuple(target.split(".")), int(detail))
    if kind == "manifest-junk":
        (session / "manifest.json").write_bytes(detail)
        return True
    if kind == "junk-file":
        path = session / target
        path.parent.mkdir(exist_ok=True)
        path.write_bytes(detail)
        return False  # wrong only for the commands that read that file (see _refused)
    if kind == "derived-symlink-out":
        shutil.rmtree(session / "derived")
        (session / "derived").symlink_to(outside, target_is_directory=True)
        return False
    if kind == "derived-fifo":
        shutil.rmtree(session / "derived")
        os.mkfifo(session / "derived")
        return False
    csv = session / "streams" / f"{target}.csv"
    lines = _lines(csv)
    body = lines[1:]
    row = 1 + (int(detail) % max(1, len(body) - 2))  # a middle row, never the header or the last line
    if kind in ("cell-junk", "cell-overflow"):
        cells = lines[row].rstrip(b"\n").split(b",")
        column = 1 if kind == "cell-overflow" else 1 + int(detail) % (len(cells) - 1)  # t_host_ns / any
        cells[column] = b"123456789012345678901234" if kind == "cell-overflow" else b"abc"
        lines[row] = b",".join(cells) + b"\n"
    elif kind == "non-utf8":
        lines[row] = lines[row][:5] + b"\xff\xfe\xfd" + lines[row][5:]
    elif kind == "time-backwards":  # two neighbouring rows swap their host times
        a, b = lines[row].split(b","), lines[row + 1].split(b",")
        a[1], b[1] = b[1], a[1]
        lines[row], lines[row + 1] = b",".join(a), b",".join(b)
    elif kind == "torn-tail":
        last = lines[-1]
        lines[-1] = last[: 1 + int(detail) % max(1, len(last) - 2)]
    elif kind == "garbage-line":
        lines.insert(row, b"this is not a row of this stream\n")
    elif kind == "fifo":
        csv.unlink()
        os.mkfifo(csv)
        (session / "streams" / f"{target}.npy").unlink(missing_ok=True)
        return True
    elif kind == "missing":
        csv.unlink()
        (session / "streams" / f"{target}.npy").unlink(missing_ok=True)
        return True
    elif kind == "directory":
        csv.unlink()
        csv.mkdir()
        (session / "streams" / f"{target}.npy").unlink(missing_ok=True)
        return True
    elif kind == "symlink-out":  # the stream's file is a link to a copy outside the session
        copy = outside / f"{target}.csv"
        copy.write_bytes(csv.read_bytes())
        csv.unlink()
        csv.symlink_to(copy)
        return False
    elif kind == "npy-junk":
        npy = session / "streams" / f"{target}.npy"
        npy.write_bytes(b"\x93NUMPY junk" + bytes(int(detail) % 97))
        return False  # the CSV is intact: falling back to it (with a warning) is a right answer
    csv.write_bytes(b"".join(lines))
    # a torn last line is what a crash leaves (use the whole lines, warn); host time stepping back is
    # what the original system's importer keeps (flag it): both may be read, never quietly
    return kind not in DOUBTFUL


def _refused(damage: Damage, command: str, wrong_for_all: bool) -> bool:
    """Must ``command`` exit non-zero on this damage?"""
    if command == "repair":
        return False  # repairing damage is its job; whether it can is its call
    if command == "verify":
        return wrong_for_all or damage.kind in ("torn-tail", "symlink-out", "npy-junk")
    if damage.kind == "junk-file":
        readers = {"labels/gestures.csv": {"labels-stats"}, "derived/pedals_gt.csv": {"eval-pedals"}}
        return command in readers.get(damage.target, set())
    if damage.kind in ("derived-symlink-out", "derived-fifo"):
        return command in WRITERS
    manifest_damage = damage.kind.startswith("manifest") or damage.kind == "stream-field-type"
    if command in ("info", "labels-stats", "eval-pedals", "eval-correlation"):
        # eval reads the aligned table align made before the damage, not the streams themselves
        return manifest_damage
    return wrong_for_all


# -------------------------------------------------------------------------------------------- running

def _release_fifos(root: Path) -> None:
    """Open the write end of every FIFO under ``root`` and close it: a reader blocked in open() then
    sees end-of-file and its thread can finish (the test reports the hang itself)."""
    for path in root.rglob("*"):
        with contextlib.suppress(OSError):
            if stat.S_ISFIFO(path.lstat().st_mode):
                os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))


def run_midas(args: list[str], release: Path) -> tuple[int | None, str]:
    """Run the `midas` entry point in this process; (exit code or None if hung, stdout + stderr)."""
    both = io.StringIO()
    code = run_in_process(args, both, both, HANG_S, on_hang=lambda: _release_fifos(release))
    return code, both.getvalue()


def snapshot(root: Path, skip: Path | None = None) -> dict[str, str]:
    """Every entry under ``root`` (not following links; ``skip`` left out): what it is and holds."""
    entries: dict[str, str] = {}
    for path in sorted(root.rglob("*")):
        if skip is not None and (path == skip or skip in path.parents):
            continue
        mode = path.lstat().st_mode
        if stat.S_ISLNK(mode):
            entries[str(path)] = "link:" + os.readlink(path)
        elif stat.S_ISREG(mode):
            entries[str(path)] = hashlib.sha256(path.read_bytes()).hexdigest()
        else:
            entries[str(path)] = f"mode:{stat.S_IFMT(mode)}"
    return entries


def _recorded(entries: dict[str, str], session: Path) -> dict[str, str]:
    """The entries a reading command must leave alone: all but outputs under derived/."""
    derived = session / "derived"
    return {k: v for k, v in entries.items() if not (Path(k) == derived or derived in Path(k).parents)
            or v.startswith("link:") or v.startswith("mode:")}


# ------------------------------------------------------------------------------------------- the test

@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("property-pristine")
    result = midas("simulate", "dataset", "--out", str(root), "--trials", "1", "--max-seconds", "6", "--seed", "5")
    assert result.returncode == 0, result.stderr
    session = next(root.iterdir())
    for command in COMMANDS.values():  # derived outputs exist before the damage, as in a used session
        if command[0] in ("align", "eval"):
            code, text = run_midas([a.format(s=session) for a in command], session)
            assert code == 0, text
    return session


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_reader_accepts_the_undamaged_session(pristine: Path, tmp_path: Path, command: str) -> None:
    session = tmp_path / pristine.name
    shutil.copytree(pristine, session, symlinks=True)
    code, text = run_midas([a.format(s=session) for a in COMMANDS[command]], session)
    assert code == 0, text


@settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(damage=damages, command=st.sampled_from(sorted(COMMANDS)))
def test_damaged_sessions_are_refused_or_read_honestly_never_crash_or_escape(
        pristine: Path, tmp_path_factory, damage: Damage, command: str) -> None:
    workspace = tmp_path_factory.mktemp("property")
    session, outside = workspace / pristine.name, workspace / "outside"
    shutil.copytree(pristine, session, symlinks=True)
    outside.mkdir()
    (outside / "keep.txt").write_text("not midas's\n")
    wrong = apply(damage, session, outside)
    before_outside = snapshot(workspace, skip=session)
    before_inside = _recorded(snapshot(session), session)

    code, text = run_midas([a.format(s=session) for a in COMMANDS[command]], session)

    what = f"`midas {' '.join(COMMANDS[command][:-1])}` on {damage}"
    assert code is not None, f"{what} hung for {HANG_S} s"
    assert code in (0, 2, 3, 4), f"{what} exited {code}: {text[-2000:]}"
    assert "Traceback" not in text, f"{what} printed a traceback: {text[-2000:]}"
    assert snapshot(workspace, skip=session) == before_outside, f"{what} wrote outside the session"
    if command != "repair":
        assert _recorded(snapshot(session), session) == before_inside, f"{what} changed the recorded session"
    if _refused(damage, command, wrong):
        assert code != 0, f"{what} exited 0 on input it must refuse: {text[-2000:]}"
    if code == 0 and damage.kind in DOUBTFUL and command == "align":
        said = [line for line in text.splitlines() if "warning" in line.lower()]
        assert any(f"{damage.target}.csv" in line for line in said), f"{what} used it without a word: {text[-2000:]}"


# ------------------------------------------------------------------ issue 23: manifest strings as names

NAME_EXAMPLES = max(20, EXAMPLES // 6)
# strings no name may be, wherever they come from: whole values, and pieces that spoil any value
ABSOLUTE = "/tmp/midas-property-absolute"  # checked for after each run: it is outside the workspace
HOSTILE_WHOLE = ["..", ".", "", "../X", "../../X", ABSOLUTE, "streams/../../X", "x" * 300, "Ωmega"]
HOSTILE_PIECES = ["/", "../", "\n", "\r", "\x00", "\\", "\t", " ", "\x7f", "é", "名", "\u202e"]
hostile_names = st.one_of(
    st.sampled_from(HOSTILE_WHOLE),
    st.builds(lambda head, piece, tail: head + piece + tail, st.text("abcXYZ019_-.", max_size=12),
              st.sampled_from(HOSTILE_PIECES), st.text("abcXYZ019_-.", max_size=12)),
)
# where a session's strings become part of a path: the manifest's names, and a label set's file name
NAME_FIELDS = ["session_id", "stream key", "device key", "stream device", "label set file"]
# commands with an --out ({o}, under the workspace) or none: none may write outside --out or derived/
NAME_COMMANDS = {
    "verify": ["session", "verify", "{s}"],
    "export": ["export", "{s}", "--format", "mcap,parquet,xdf", "--out", "{o}"],
    "plot": ["plot", "{s}", "--out", "{o}/page.png"],
    "labels-export": ["labels", "export", "{s}", "--format", "via", "--out", "{o}/labels.json"],
}


def _name_damage(session: Path, field: str, name: str) -> None:
    """Put ``name`` where ``field`` is: a manifest name, or the file name of a copy of a label set."""
    if field == "label set file":
        shutil.copy(session / "labels" / "gestures.csv", session / "labels" / f"{name}.csv")
        return
    manifest = json.loads((session / "manifest.json").read_text())
    if field == "session_id":
        manifest["session_id"] = name
    elif field == "stream key":
        manifest["streams"] = {name if k == "emht" else k: v for k, v in manifest["streams"].items()}
    elif field == "device key":
        manifest["devices"][name] = {"kind": "test"}
    else:
        manifest["streams"]["emht"]["device"] = name
    (session / "manifest.json").write_text(json.dumps(manifest))


def _can_be_file_name(name: str) -> bool:
    return "/" not in name and "\x00" not in name and name not in ("", ".", "..") and len(name.encode()) < 250


@settings(max_examples=NAME_EXAMPLES, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(field=st.sampled_from(NAME_FIELDS), name=hostile_names, command=st.sampled_from(sorted(NAME_COMMANDS)))
def test_manifest_strings_used_as_names_are_refused_and_never_name_files_outside_the_out_folder(
        pristine: Path, tmp_path_factory, field: str, name: str, command: str) -> None:
    if field == "label set file" and not _can_be_file_name(name):
        name = name.replace("/", "_").replace("\x00", "_").strip(".")[:200] + "\n"  # still no label set name
    workspace = tmp_path_factory.mktemp("names")
    session, out = workspace / pristine.name, workspace / "out"
    shutil.copytree(pristine, session, symlinks=True)
    _name_damage(session, field, name)
    before_outside = snapshot(workspace, skip=session)
    before_inside = _recorded(snapshot(session), session)

    args = [a.format(s=session, o=out) for a in NAME_COMMANDS[command]]
    code, text = run_midas(args, session)

    what = f"`midas {' '.join(NAME_COMMANDS[command][:2])}` with {field} = {name!r}"
    assert code in (0, 2, 4) and "Traceback" not in text, f"{what} exited {code}: {text[-2000:]}"
    written = {k for k in set(snapshot(workspace, skip=session)) - set(before_outside)}
    assert all(Path(k) == out or out in Path(k).parents for k in written), f"{what} wrote outside --out: {written}"
    assert not list(Path(ABSOLUTE).parent.glob(Path(ABSOLUTE).name + "*")), f"{what} wrote {ABSOLUTE}"
    assert _recorded(snapshot(session), session) == before_inside, f"{what} changed the recorded session"
    if field != "label set file":  # the manifest is read by every command: one line, naming the field
        lines = text.strip().splitlines()
        assert code == 4 and len(lines) == 1, f"{what} was not refused in one line: {text[-2000:]}"
        assert ("session_id" if field == "session_id" else "streams" if "stream" in field else "devices") in lines[0]
    elif command != "labels-export":  # these read every label set (labels export: only the one it exports)
        assert code == 4, f"{what} exited {code}: {text[-2000:]}"
        if command == "verify":
            assert len([line for line in text.splitlines() if "problem:" in line]) == 1, text
