"""Issue 14 items 4 and 8: every failure is one `midas: error: ...` line with the documented exit code
(2 bad option value, 4 bad file or full disk), and long commands print plain progress lines when
stderr is not a terminal."""

from __future__ import annotations

import json
import os
import pickle
import shutil
import textwrap
from pathlib import Path

import pytest
from helpers.cli import midas, write_session
from helpers.gesture_sessions import write_gesture_dataset

from midas_cli.commands.progress import PlainProgress, progress_line


def assert_one_error(result, code: int, *needles: str) -> None:
    """Exit ``code``, stderr exactly one `midas: error:` line mentioning every needle, no traceback."""
    lines = result.stderr.strip().splitlines()
    assert result.returncode == code, result.stderr
    assert len(lines) == 1 and lines[0].startswith("midas: error: "), result.stderr
    assert "Traceback" not in result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


@pytest.fixture(scope="module")
def gestures(tmp_path_factory) -> list[Path]:
    return write_gesture_dataset(tmp_path_factory.mktemp("gestures"), n_trials=4, n_frames=120)


def copy_session(session: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(session, tmp_path / session.name))


# --- bad option values: exit 2, the option named -------------------------------------------------

@pytest.mark.parametrize("args, option", [
    (["labels", "stats", "{t}", "--frame-rate", "0"], "--frame-rate"),
    (["labels", "stats", "{t}", "--frame-rate", "nan"], "--frame-rate"),
    (["simulate", "console-video", "--out", "{d}/v.mkv", "--duration", "nan"], "--duration"),
    (["calibrate", "emht", "{d}", "--weight-decay", "nan"], "--weight-decay"),
    (["emulate", "fps", "--corrupt", "2"], "--corrupt"),
])
def test_bad_number_is_exit_2_naming_the_option(tmp_path, args, option):
    transcription = tmp_path / "t.txt"
    transcription.write_text("1 10 G1\n11 30 G2\n")
    result = midas(*(a.format(t=transcription, d=tmp_path) for a in args))
    assert_one_error(result, 2, option)
    assert not (tmp_path / "v.mkv").exists()


def test_unknown_ablation_model_is_exit_2_before_training(gestures, tmp_path):
    result = midas("train", "ablation", *map(str, gestures), "--models", "bogus,mstcn", "--grid", "emht:pos",
                   "--epochs", "1", "--out", str(tmp_path / "abl"))
    assert_one_error(result, 2, "--models", "bogus")
    assert not (tmp_path / "abl").exists()


# --- bad files: exit 4, the file named ------------------------------------------------------------

@pytest.mark.parametrize("name, content", [
    ("gestures.csv", b"garbage\n"),
    ("gestures.csv", b"frame,label\nx,G1\n"),
    ("gestures.csv", b"\xff\xfe\x00junk"),
    ("gestures.json", b"{not json"),
    ("gestures.json", b"[1, 2]"),
])
def test_junk_label_file_is_exit_4_naming_it(gestures, tmp_path, name, content):
    session = copy_session(gestures[0], tmp_path)
    (session / "labels" / name).write_bytes(content)
    assert_one_error(midas("labels", "stats", str(session)), 4, f"labels/{name}")


def test_damaged_aligned_npz_is_exit_4_naming_it(gestures, tmp_path):
    session = copy_session(gestures[0], tmp_path)
    (session / "derived" / "aligned.npz").write_bytes(b"PK\x03\x04" + b"\x00" * 40)  # a zip that is not one
    result = midas("train", "gestures", str(session), "--model", "mstcn", "--epochs", "1", "--out", str(tmp_path / "run"))
    assert_one_error(result, 4, "aligned.npz")


@pytest.mark.parametrize("content", [b"", pickle.dumps(Path("a-python-object"))], ids=["empty", "pickled"])
def test_bad_checkpoint_is_exit_4_naming_it(gestures, tmp_path, content):
    checkpoint = tmp_path / "checkpoint.pt"
    checkpoint.write_bytes(content)
    result = midas("train", "gestures", *map(str, gestures), "--eval-only", str(checkpoint), "--out", str(tmp_path / "ev"))
    assert_one_error(result, 4, str(checkpoint))


def test_empty_backbone_weights_is_exit_4_not_aborted(tmp_path):
    weights = tmp_path / "resnet50.pth"
    weights.write_bytes(b"")
    result = midas("extract", "image-features", str(tmp_path / "v.mkv"), "--backbone", "resnet50", "--weights", str(weights),
                   "--out", str(tmp_path / "f.npz"))
    assert_one_error(result, 4, str(weights))
    assert "Aborted" not in result.stderr


def test_pickled_calibration_mlp_is_exit_4_naming_it(tmp_path):
    from midas_cli.models.residual_mlp import load_mlp  # torch: imported by this test only
    from midas_cli.errors import SessionError

    weights = tmp_path / "emht_to_mtm.pt"
    weights.write_bytes(pickle.dumps(Path("a-python-object")))
    description = {"config": {"hidden": [4], "dropout": 0.0}, "x_mean": [0.0], "x_std": [1.0], "y_mean": [0.0],
                   "y_std": [1.0]}
    with pytest.raises(SessionError, match="emht_to_mtm.pt"):
        load_mlp(weights, description)


VIA_BREAKERS = {
    "file is a list": lambda via: via.__setitem__("file", []),
    "a view is a number": lambda via: via["view"].__setitem__("1", 5),
    "metadata entry is text": lambda via: via["metadata"].__setitem__(next(iter(via["metadata"])), "x"),
    "options is a list": lambda via: next(iter(via["attribute"].values())).__setitem__("options", ["G1"]),
}


@pytest.mark.parametrize("breaker", VIA_BREAKERS, ids=list(VIA_BREAKERS))
def test_via_file_with_wrong_types_is_exit_4_naming_it(gestures, tmp_path, breaker):
    session = copy_session(gestures[0], tmp_path)
    exported = midas("labels", "export", str(session), "--format", "via", check=True).stdout
    via = json.loads(exported)
    VIA_BREAKERS[breaker](via)
    bad = tmp_path / "bad_via.json"
    bad.write_text(json.dumps(via))
    result = midas("labels", "import-via", str(bad), str(session), "--taxonomy", "jigsaws-suturing", "--force",
                   "--name", "reimported")
    assert_one_error(result, 4, "bad_via.json")


# --- a full disk: one line, exit 4, nothing lost ---------------------------------------------------

FULL_DISK = textwrap.dedent('''
    import errno, os, sys
    UNDER, MATCH = os.environ["FULL_DISK_UNDER"], os.environ.get("FULL_DISK_MATCH", "")
    BESIDE = os.environ.get("FULL_DISK_BESIDE", "")
    def full(event, args):  # every file opened for writing under UNDER (whose path has MATCH): ENOSPC
        if event != "open" or not isinstance(args[0], (str, bytes, os.PathLike)):
            return
        path, mode, flags = os.path.abspath(os.fsdecode(args[0])), args[1], args[2]
        writing = any(c in mode for c in "wax+") if mode else bool((flags or 0) & (os.O_WRONLY | os.O_RDWR | os.O_CREAT))
        beside = not BESIDE or os.path.exists(os.path.join(os.path.dirname(path), BESIDE))  # (once BESIDE exists)
        if writing and path.startswith(UNDER) and MATCH in path and beside:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), path)
    sys.addaudithook(full)
''')


def full_disk_env(tmp_path: Path, under: Path, match: str = "", beside: str = "") -> dict[str, str]:
    """Environment whose Python sees a full disk under ``under`` (a sitecustomize audit hook), for
    paths holding ``match`` (and, with ``beside``, only once a file of that name is beside them)."""
    hook = tmp_path / "hook"
    hook.mkdir(exist_ok=True)
    (hook / "sitecustomize.py").write_text(FULL_DISK)
    return {"PYTHONPATH": os.pathsep.join([str(hook), os.environ.get("PYTHONPATH", "")]),
            "FULL_DISK_UNDER": str(under.resolve()), "FULL_DISK_MATCH": match, "FULL_DISK_BESIDE": beside}


def assert_disk_full(result, path_part: str) -> None:
    assert_one_error(result, 4, "disk full / read-only:", path_part)


def test_align_on_a_full_disk_keeps_the_old_table_and_leaves_no_temporaries(gestures, tmp_path):
    session = copy_session(gestures[0], tmp_path)
    before = {p.name: p.read_bytes() for p in (session / "derived").iterdir()}
    result = midas("align", str(session), env=full_disk_env(tmp_path, session / "derived"))
    assert_disk_full(result, "aligned")
    assert {p.name: p.read_bytes() for p in (session / "derived").iterdir()} == before


def test_repair_on_a_full_disk_loses_nothing_and_can_run_again(tmp_path):
    session = write_session(tmp_path / "sessions", rows=20)
    manifest = json.loads((session / "manifest.json").read_text())
    (session / "manifest.json").write_text(json.dumps({**manifest, "status": "recording"}))
    stream = session / "streams" / "demo.csv"
    with open(stream, "ab") as fh:
        fh.write(b"20,123")  # a torn last line
    data = stream.read_bytes()
    result = midas("session", "repair", str(session), env=full_disk_env(tmp_path, session, "demo.csv"))
    assert_disk_full(result, "demo.csv")
    cut = session / "logs" / "repair-demo.cut"
    assert stream.read_bytes() + (cut.read_bytes() if cut.exists() else b"") in (data, data + b"20,123")
    midas("session", "repair", str(session), check=True)  # with room again
    assert stream.read_bytes() + cut.read_bytes() == data
    assert json.loads((session / "manifest.json").read_text())["status"] == "recovered"


def test_record_on_a_full_disk_is_exit_4_and_names_the_folder_it_made(tmp_path):
    out = tmp_path / "rec"
    out.mkdir()
    result = midas("record", "--simulate", "--duration", "1", "--out", str(out), "--subject", "1", "--task", "t",
                   "--trial", "1", env=full_disk_env(tmp_path, out, "midas.log"))
    assert_disk_full(result, "midas.log")
    (session,) = out.iterdir()  # made before the log could not be: `path=$(midas record ... | tail -n 1)` finds it
    assert result.stdout.splitlines()[-1] == str(session)


def _files_of_200_kb() -> None:
    """Every file the recorder writes may grow to 200 kB: a stream's write fails (a row is dropped)."""
    import resource
    import signal

    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))


@pytest.mark.parametrize("mode", ["--no-tui", "--status-json"])
def test_record_without_room_for_its_final_manifest_names_the_folder_and_repair_keeps_how_it_ended(tmp_path, mode):
    """The disk fills during a recording (a row read but not written) and leaves no room for the final
    manifest either (manifest.json can be written once, never replaced)."""
    out = tmp_path / "rec"
    out.mkdir()
    result = midas("record", "--simulate", "--duration", "30", "--out", str(out), "--subject", "1", "--task", "t",
                   "--trial", "1", mode, env=full_disk_env(tmp_path, out, "manifest.json.tmp", beside="manifest.json"),
                   preexec_fn=_files_of_200_kb, timeout=90)
    assert result.returncode == 4 and "Traceback" not in result.stderr, result.stderr
    assert "midas session repair" in result.stderr.strip().splitlines()[-1]
    (session,) = out.iterdir()
    last = result.stdout.splitlines()[-1]
    if mode == "--status-json":
        final = json.loads(last)
        assert final["event"] == "stopped" and final["status"] == "recording"
        assert final["session_path"] == str(session) and "midas session repair" in final["reason"]
    else:
        assert last == str(session)
    assert json.loads((session / "manifest.json").read_text())["status"] == "recording"
    midas("session", "repair", str(session), check=True)
    manifest = json.loads((session / "manifest.json").read_text())
    assert manifest["status"] == "recovered" and "File too large" in manifest["stop_reason"]
    assert "writing the session failed" in manifest["stop_reason"] and "status interrupted" in manifest["stop_reason"]
    assert sum(entry.get("dropped", 0) for entry in manifest["streams"].values()) >= 1
    assert not (session / "logs" / "stop-facts.json").exists()
    midas("session", "verify", str(session), check=True)


# --- progress when nobody is looking at a terminal ------------------------------------------------

def test_train_prints_plain_progress_lines_when_stderr_is_not_a_terminal(gestures, tmp_path):
    env = {"MIDAS_PROGRESS_INTERVAL_S": "0"}
    result = midas("train", "gestures", *map(str, gestures), "--model", "mstcn", "--epochs", "2", "--out", str(tmp_path / "run"), env=env)
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.startswith("midas: progress: ")]
    assert [line.split(",")[0] for line in lines] == ["midas: progress: mstcn epochs: 1/2 (50%)",
                                                       "midas: progress: mstcn epochs: 2/2 (100%)"]
    assert all("elapsed " in line and "ETA " in line and "loss " in line for line in lines)
    assert "━" not in result.stderr  # no rich bar in a log file


def test_bad_progress_interval_is_exit_2(gestures, tmp_path):
    env = {"MIDAS_PROGRESS_INTERVAL_S": "soon"}
    assert_one_error(midas("align", str(copy_session(gestures[0], tmp_path)), env=env), 2, "MIDAS_PROGRESS_INTERVAL_S")


def test_plain_progress_waits_the_interval_between_lines():
    now, lines = [0.0], []
    progress = PlainProgress(10.0, clock=lambda: now[0], write=lines.append)
    task = progress.add_task("aligning sessions", total=4)
    for t in (1.0, 2.0, 12.0, 13.0):
        now[0] = t
        progress.advance(task)
    assert lines == [progress_line("aligning sessions", 1, 4, 1.0), progress_line("aligning sessions", 3, 4, 12.0),
                     progress_line("aligning sessions", 4, 4, 13.0)]  # the last: the task is done
    assert lines[0] == "midas: progress: aligning sessions: 1/4 (25%), elapsed 00:00:01, ETA 00:00:03"


def test_progress_line_without_a_total_says_the_eta_is_unknown():
    assert progress_line("hand keypoints", 7, None, 65.0) == \
        "midas: progress: hand keypoints: 7 done, elapsed 00:01:05, ETA unknown"
    assert progress_line("x", 0, 5, 0.0).endswith("ETA unknown")


@pytest.mark.parametrize("args, needles", [
    (["export", "{d}", "--formt", "mcap", "--out", "{d}/x"], ["export:", "--formt", "--format"]),
    (["session", "verify"], ["session verify:", "Missing argument"]),
    (["record", "--simulate", "--duration", "abc"], ["record:", "--duration"]),
    (["bogus"], ["No such command", "bogus"]),
])
def test_click_usage_errors_are_one_line_and_a_hint(tmp_path, args, needles):
    """A typo in an option was a usage line and a 3-line box; now one `midas: error:` line, then the hint."""
    result = midas(*(a.format(d=tmp_path) for a in args))
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 2, result.stderr
    assert lines[0].startswith("midas: error: ") and all(n in lines[0] for n in needles), lines[0]
    assert lines[1].startswith("Try 'midas") and lines[1].endswith(" -h' for help.")
    assert not (tmp_path / "x").exists() and not result.stdout
