"""Issue 23, item 2: a session folder is data from someone else, and its strings name files.

Every manifest or label string that becomes part of a path (session_id, device and stream names, the
files the manifest lists, label set names) is checked where the session is read: `session verify`
refuses such a session with one line naming the field, every analysis command refuses it (exit 4), and
the writers put data-named files through ``outputs.out_child`` anyway. An ``--out`` that is one of the
command's inputs is refused (exit 2): `labels export --out S/labels/gestures.csv` overwrote the label set
it exported.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from helpers.cli import midas
from helpers.gesture_sessions import write_gesture_session
from midas_cli.errors import ConfigError, SessionError
from midas_cli.session.manifest import load_manifest
from midas_cli.session.names import check_name, is_name
from midas_cli.session.outputs import out_child, out_target
from midas_cli.session.reader import Session

BAD_PATHS = ["../../X", "/abs/path", "..", ".", "", "x\ny", "x\u0000y", "a\\b", "streams/../../X"]
BAD_NAMES = BAD_PATHS + ["a/b", "x" * 300, "naïve", " x"]


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small finished session with a video stream, labels/gestures.* and an aligned table."""
    return write_gesture_session(tmp_path_factory.mktemp("names"), "1", 1, n_frames=120)


def _copy(pristine: Path, root: Path) -> Path:
    session = root / "in" / pristine.name
    shutil.copytree(pristine, session)
    return session


def _edit(session: Path, change) -> None:
    path = session / "manifest.json"
    manifest = json.loads(path.read_text())
    change(manifest)
    path.write_text(json.dumps(manifest))


def _rename_stream(manifest: dict, old: str, new: str) -> None:
    manifest["streams"] = {new if k == old else k: v for k, v in manifest["streams"].items()}


def _files(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def _one_error_line(result, field: str) -> None:
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and field in lines[0] and "Traceback" not in result.stderr, result.stderr


# ------------------------------------------------------------------------- the reproductions, end to end

def test_a_climbing_session_id_is_refused_by_verify_export_and_train(pristine: Path, tmp_path: Path) -> None:
    session = _copy(pristine, tmp_path)
    _edit(session, lambda m: m.update(session_id="../../X"))
    work = tmp_path / "work"
    work.mkdir()
    before = _files(tmp_path)

    verify = midas("session", "verify", str(session))
    assert verify.returncode == 4 and "OK" not in verify.stdout
    _one_error_line(verify, "session_id")
    export = midas("export", str(session), "--format", "mcap", "--out", "a/b/out", cwd=work)
    assert export.returncode == 4
    _one_error_line(export, "session_id")
    train = midas("train", "gestures", str(session), "--model", "mstcn", "--epochs", "1", "--out", str(work / "run"))
    assert train.returncode == 4
    _one_error_line(train, "session_id")
    # nothing anywhere but the --out folder train makes first (empty): no X.mcap, X.csv, X.png
    assert _files(tmp_path) - before <= {"work/run"}


def test_a_stream_key_that_is_an_absolute_path_is_refused_by_verify_and_export(pristine: Path,
                                                                                tmp_path: Path) -> None:
    session = _copy(pristine, tmp_path)
    target = tmp_path / "abs" / "path"
    _edit(session, lambda m: _rename_stream(m, "video", str(target)))

    verify = midas("session", "verify", str(session))
    assert verify.returncode == 4
    _one_error_line(verify, "a key of streams")
    export = midas("export", str(session), "--format", "parquet", "--out", str(tmp_path / "out"))
    assert export.returncode == 4
    _one_error_line(export, "a key of streams")
    assert not (tmp_path / "abs").exists() and not (tmp_path / "out").exists()


@pytest.mark.parametrize("command", [["align", "{s}"], ["plot", "{s}"], ["labels", "export", "{s}", "--format", "csv"],
                                     ["session", "info", "{s}"]])
def test_analysis_commands_refuse_a_device_name_that_climbs_out(pristine: Path, tmp_path: Path,
                                                                command: list[str]) -> None:
    session = _copy(pristine, tmp_path)
    _edit(session, lambda m: m["streams"]["video"].update(device="../video"))
    result = midas(*[a.format(s=session) for a in command])
    assert result.returncode == 4
    _one_error_line(result, "streams.video.device")


def test_repair_refuses_a_climbing_stream_name_with_one_line(pristine: Path, tmp_path: Path) -> None:
    session = _copy(pristine, tmp_path)

    def crashed(manifest: dict) -> None:  # a recording left by a crash, its stream renamed
        manifest.update(status="recording", stop=None)
        _rename_stream(manifest, "video", "../../video")

    _edit(session, crashed)
    with open(session / "streams" / "video.csv", "a") as fh:
        fh.write("999,17")  # a torn last line: repair would save it to logs/repair-<name>.cut
    before = _files(tmp_path)
    result = midas("session", "repair", str(session))
    assert result.returncode == 4
    _one_error_line(result, "a key of streams")
    assert _files(tmp_path) == before


def test_labels_export_refuses_to_overwrite_the_label_set_it_reads(pristine: Path, tmp_path: Path) -> None:
    session = _copy(pristine, tmp_path)
    labels = session / "labels" / "gestures.csv"
    kept = labels.read_bytes()
    for out in (labels, session / "labels" / ".." / "labels" / "gestures.json"):
        result = midas("labels", "export", str(session), "--format", "csv", "--out", str(out))
        assert result.returncode == 2
        _one_error_line(result, "which this command reads")
    assert labels.read_bytes() == kept


@pytest.mark.parametrize("command, read", [(["calibrate", "fps-optimize", "{s}"], "derived/aligned.json"),
                                           (["plot", "{s}"], "labels/gestures.csv")])
def test_other_commands_refuse_an_out_that_is_one_of_their_inputs(pristine: Path, tmp_path: Path,
                                                                  command: list[str], read: str) -> None:
    session = _copy(pristine, tmp_path)
    kept = (session / read).read_bytes()
    result = midas(*[a.format(s=session) for a in command], "--out", str(session / read))
    assert result.returncode == 2
    _one_error_line(result, "which this command reads")
    assert (session / read).read_bytes() == kept


def test_verify_refuses_a_label_set_file_whose_name_no_label_set_may_have(pristine: Path, tmp_path: Path) -> None:
    session = _copy(pristine, tmp_path)
    shutil.copy(session / "labels" / "gestures.csv", session / "labels" / "two\nlines.csv")
    result = midas("session", "verify", str(session))
    assert result.returncode == 4
    problems = [line for line in result.stdout.splitlines() if "problem:" in line]
    assert len(problems) == 1 and "label set" in problems[0] and "two\\nlines" in problems[0], result.stdout
    named = midas("labels", "export", str(session), "--format", "csv", "--name", "../gestures")
    assert named.returncode == 4
    _one_error_line(named, "label set name")


# ------------------------------------------------------------------------------ the rule, in-process

@pytest.mark.parametrize("bad", BAD_NAMES)
def test_every_name_field_refuses_what_is_not_one_plain_name(pristine: Path, tmp_path: Path, bad: str) -> None:
    session = _copy(pristine, tmp_path)
    original = (session / "manifest.json").read_text()
    edits = {"session_id": lambda m: m.update(session_id=bad),
             "a key of streams": lambda m: _rename_stream(m, "video", bad),
             "a key of devices": lambda m: m.update(devices={bad: {"kind": "test"}}),
             "streams.video.device": lambda m: m["streams"]["video"].update(device=bad)}
    if bad in BAD_PATHS:  # a file the manifest lists may be a path inside the session, never one out of it
        edits["streams.video.file"] = lambda m: m["streams"]["video"].update(file=bad)
        edits["files.log"] = lambda m: m["files"].update(log=bad)
    for field, edit in edits.items():
        (session / "manifest.json").write_text(original)
        _edit(session, edit)
        with pytest.raises(SessionError) as refused:
            load_manifest(session)
        message = str(refused.value)
        assert field in message and "\n" not in message and len(message) < 500, message


def test_binary_copy_paths_are_checked_like_the_stream_files(pristine: Path, tmp_path: Path) -> None:
    session = _copy(pristine, tmp_path)
    _edit(session, lambda m: m["streams"]["video"].update(binary={"file": "../../elsewhere.npy", "rows": 1,
                                                                 "csv_sha256": "x"}))
    with pytest.raises(SessionError, match="streams.video.binary.file"):
        load_manifest(session)


def test_the_names_midas_itself_writes_pass() -> None:
    assert is_name("suturing_S1_T3_20260101T120000Z_2", "session id")
    assert is_name("demo_S1.5_T1_20231114T221320Z", "session id")
    assert is_name("obs_marker", "stream") and is_name("smartwatch_left_acc", "stream")
    assert is_name("a" * 32, "device") and not is_name("a" * 33, "device")
    assert is_name("a" * 64, "stream") and not is_name("a" * 65, "stream")
    assert not is_name("emht\n", "device")  # `$` of a regex would have let the newline through
    with pytest.raises(ConfigError, match="device name"):
        check_name("1emht", "device", "device name", ConfigError)


@pytest.mark.parametrize("bad", ["..", ".", "", "a/b", "../x", "/etc/x", "x\ny", "x\u0000y", "x" * 256])
def test_out_child_keeps_data_named_files_in_the_output_folder(tmp_path: Path, bad: str) -> None:
    with pytest.raises(SessionError, match="one plain file name"):
        out_child(tmp_path, bad)
    assert out_child(tmp_path, "session_1.mcap") == tmp_path.resolve() / "session_1.mcap"


def test_out_child_refuses_a_link_that_leads_out_of_the_folder(tmp_path: Path) -> None:
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "s.mcap").symlink_to(tmp_path / "elsewhere.mcap")
    with pytest.raises(SessionError):
        out_child(tmp_path / "out", "s.mcap")


def test_writers_confine_data_named_files_even_when_the_manifest_was_not_checked(pristine: Path,
                                                                               tmp_path: Path) -> None:
    from midas_cli.interop.parquet_export import write_parquet

    session = Session.open(_copy(pristine, tmp_path))
    _rename_stream(session.manifest, "video", "../../escaped")  # as if a reader had skipped validation
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(SessionError, match="one plain file name"):
        write_parquet(session, out)
    assert not list(tmp_path.rglob("escaped*"))


def test_out_target_refuses_its_inputs_through_links(tmp_path: Path) -> None:
    data = tmp_path / "data.csv"
    data.write_text("x\n")
    (tmp_path / "link.csv").symlink_to(data)
    with pytest.raises(ConfigError, match="which this command reads"):
        out_target(tmp_path / "link.csv", inputs=[data])
    assert out_target(tmp_path / "other.csv", inputs=[data]) == tmp_path.resolve() / "other.csv"


def test_a_session_whose_stream_names_are_refused_leaves_no_folder(tmp_path: Path) -> None:
    """An importer names streams from the files it reads (a watch's sensor): the manifest's check
    refuses the name before any stream file exists, and the half-made folder goes."""
    from midas_cli.clock import HostClock
    from midas_cli.session.schema import SEQ, T_HOST, StreamSpec
    from midas_cli.session.writer import SessionMetadata, SessionWriter

    spec = StreamSpec("smartwatch_left_../../x", "smartwatch_left", (SEQ, T_HOST), 50.0)
    with pytest.raises(SessionError, match="a key of streams"):
        SessionWriter.create(tmp_path / "out", SessionMetadata("1", "demo", 1), HostClock.anchored_now(),
                             {"smartwatch_left": {"kind": "test"}}, [spec])
    assert list((tmp_path / "out").iterdir()) == [] and not list(tmp_path.rglob("x.csv"))


def test_extract_handkp_refuses_a_stream_option_that_is_no_stream_name(tmp_path: Path) -> None:
    from midas_cli.analysis.handkp_units import plan_units

    with pytest.raises(ConfigError, match="--stream"):
        plan_units([tmp_path], "truth", None, "../derived/x", False, False)


def test_a_taxonomy_a_label_set_records_is_never_read_as_a_path(pristine: Path, tmp_path: Path) -> None:
    from midas_cli.labels.sessions import export_labels

    session = _copy(pristine, tmp_path)
    planted = tmp_path / "planted.toml"
    planted.write_text('name = "planted"\n[[gestures]]\nid = "PLANTED"\nname = "read from outside"\n')
    meta = json.loads((session / "labels" / "gestures.json").read_text())
    (session / "labels" / "gestures.json").write_text(json.dumps({**meta, "taxonomy": str(planted)}))
    assert "PLANTED" not in export_labels(session, "via")
