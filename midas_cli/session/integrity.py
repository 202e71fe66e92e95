"""`verify` (the manifest against the files) and `repair` (a session left behind by a crash).

Both also look for the temporary files the session format's writers leave when they are killed, or
the disk fills, between writing a temporary and renaming it into place (see ``find_temporaries``):
`verify` reports each, `repair` removes them. Every one is a half-made replacement of something
midas can make again (a binary copy, a derived table, a calibration), except ``manifest.json.tmp``
when ``manifest.json`` itself is missing: then it is the only manifest there is, and `repair` puts it
in place if it is complete and valid, or refuses and leaves the folder as it is."""

from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from midas_cli import __version__
from midas_cli.errors import SessionError
from midas_cli.session import stop_facts
from midas_cli.session.columnar import add_binary_copies, copy_differences
from midas_cli.session.derived import aligned_problems
from midas_cli.session.labels import list_label_sets
from midas_cli.session.manifest import (MANIFEST_NAME, MANIFEST_TMP, fsync_dir, load_manifest, read_manifest_file,
                                        write_manifest)
from midas_cli.session.outputs import is_locked, session_lock
from midas_cli.session.reader import Session
from midas_cli.session.schema import StreamSpec
from midas_cli.session.streamfile import StreamSummary, complete_line_end, summarize_bytes, summarize_stream
from midas_cli.session.values import parse_stream_bytes, read_regular_file, structured
from midas_cli.session.writer import utc_iso

if TYPE_CHECKING:
    import numpy as np

FINISHED = ("complete", "interrupted", "recovered")
TEMP_SUFFIXES = (".tmp", ".tmp.npz")  # path + ".tmp" everywhere; artifacts.write_npz: path + ".tmp.npz"
NOT_SEARCHED = ("video",)  # OBS and the RGB-D recorder write there, not the session format's writers


def find_temporaries(folder: Path | str) -> list[str]:
    """The temporary files left in a session folder by an interrupted write, relative to it, sorted.

    The session format's writers each write ``<file>.tmp`` and rename it to ``<file>``:
    ``manifest.json.tmp`` (manifest.write_manifest), ``streams/<name>.npy.tmp`` (binary copies),
    ``streams/<name>.csv.tmp`` (device_files.add_stream), ``derived/aligned.*.tmp`` (align),
    ``derived/pedals_gt.{csv,json}.tmp``, ``labels/<name>.csv.tmp``, ``calib/*.json.tmp``
    (calibrations), and any ``*.tmp`` / ``*.tmp.npz`` of artifacts.write_json / write_npz (calib/,
    derived/ or elsewhere in the folder), and the unique ``.<file>.<random>.tmp`` of
    ``outputs.replacing`` (every derived output). The whole folder is searched but ``video/``; links to
    folders are not followed."""
    root = Path(folder)
    found = []
    for dirpath, dirnames, filenames in os.walk(root):
        here = Path(dirpath)
        if here == root:
            dirnames[:] = [d for d in dirnames if d not in NOT_SEARCHED]
        found += [(here / f).relative_to(root).as_posix() for f in filenames if f.endswith(TEMP_SUFFIXES)]
    return sorted(found)


def _orphaned_manifest_problem(folder: Path) -> str | None:
    """When ``manifest.json`` is missing but ``manifest.json.tmp`` is there, what `verify` says."""
    if (folder / MANIFEST_NAME).is_file() or not (folder / MANIFEST_TMP).is_file():
        return None
    try:
        manifest = read_manifest_file(folder / MANIFEST_TMP, folder)
    except SessionError as exc:
        return (f"{MANIFEST_NAME} is missing and {MANIFEST_TMP} is not a complete manifest ({exc}): "
                f"the manifest was never written; there is nothing `midas session repair` can restore")
    return (f"{MANIFEST_NAME} is missing but {MANIFEST_TMP} holds a complete manifest (status "
            f"{manifest['status']!r}) that was never renamed into place: run `midas session repair {folder}`")


@dataclass
class VerifyReport:
    path: Path
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    streams: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.problems

    def to_json(self) -> dict[str, Any]:
        return {"path": str(self.path), "ok": self.ok, "problems": self.problems, "notes": self.notes,
                "streams": self.streams}


def verify_session(path: Path | str, strict: bool = False) -> VerifyReport:
    """Check every stream file against the manifest: presence (a regular file), header, whole lines,
    every value against its column's type and range, sample count, sha256, strictly increasing host
    time, sequence gaps, and that its binary copy (if any) holds exactly what the CSV holds. Gaps the manifest declares (a device
    outage the recorder saw) are notes, or problems with ``strict``; undeclared gaps are problems.
    Temporary files left by an interrupted write, and a recording that failed to start, are problems
    too (a failed session's streams are not checked)."""
    folder = Path(path)
    orphan = _orphaned_manifest_problem(folder) if folder.is_dir() else None
    if orphan is not None:
        return VerifyReport(folder, problems=[orphan])
    session = Session.open(folder, allow_failed=True)
    report = VerifyReport(session.path)
    locked = is_locked(session.path)
    if locked:  # a running midas command's temporaries are work in progress, not litter
        report.notes += [f"temporary file {rel}: another midas command is writing this session now"
                         for rel in find_temporaries(session.path)]
    else:
        report.problems += [f"temporary file {rel} left by an interrupted write: run `midas session repair "
                            f"{session.path}` to remove it" for rel in find_temporaries(session.path)]
    if session.status == "failed":
        reason = " ".join(str(session.manifest.get("stop_reason") or "no reason recorded").split())
        report.problems.append(f"the recording failed to start ({reason}): the session holds no data")
        return report
    if session.status not in FINISHED:
        report.problems.append(
            f"status is {session.status!r}: the recorder did not finish (run `midas session repair {session.path}`)"
        )
    for name in session.stream_names:
        _verify_stream(session, name, report, strict)
    try:  # a label set's name names files of exports, like the manifest's names
        list_label_sets(session.path)
    except SessionError as exc:
        report.problems.append(str(exc))
    if locked:  # its derived files are being replaced: checking them would wait for the writer, or see half
        report.notes.append("derived/aligned.*: not checked, another midas command is writing this session now")
    else:
        report.problems += aligned_problems(session.path)
    return report


def _verify_stream(session: Session, name: str, report: VerifyReport, strict: bool) -> None:
    entry = session.manifest["streams"][name]
    path = session.stream_path(name)
    if not path.exists():
        report.problems.append(f"{name}: file {entry['file']} is missing")
        return
    spec = session.stream_spec(name)
    try:
        data = read_regular_file(path)
    except SessionError as exc:
        report.problems.append(f"{name}: {exc}")
        return
    found = summarize_bytes(data, spec)
    report.streams[name] = {"samples": found.samples, "seq_missing": found.seq_missing,
                            "measured_rate_hz": found.measured_rate_hz}
    problems = _file_problems(found)
    parsed = None
    if found.header_ok and not found.bad_lines:
        try:  # every value against its column's type and range
            parsed = structured(parse_stream_bytes(data, spec, path).frame, spec)
        except SessionError as exc:
            problems.append(str(exc))
    if session.status in FINISHED:
        problems += _manifest_mismatches(entry, found)
    problems += _gap_findings(entry, found, strict, report.notes, name)
    if parsed is not None:
        problems += _times_outside(session, entry["file"], parsed["t_host_ns"])
    if not problems:
        problems += copy_differences(session.path, name, entry, parsed)
    report.problems.extend(f"{name}: {p}" for p in problems)


def _times_outside(session: Session, file: str, times: np.ndarray) -> list[str]:
    """The host times (ns, one per data line) outside ``session.plausible_host_ns()``: the first one's
    line and value, and how many there are (nothing when all are inside)."""
    low, high = session.plausible_host_ns()
    outside = (times < low) if high is None else (times < low) | (times > high)
    where = outside.nonzero()[0]
    if not len(where):
        return []
    first = int(where[0])
    span = f"{low} .. {'(no stop)' if high is None else high}"
    return [f"{file} line {first + 2}: t_host_ns {int(times[first])} is far outside the session's time span "
            f"(start and stop -/+ max(1 min, its length): {span}); {len(where)} such sample(s)"]


def _file_problems(found: StreamSummary) -> list[str]:
    problems = []
    if not found.header_ok:
        problems.append("header does not match the manifest's columns")
    if found.torn_tail_bytes:
        problems.append(f"torn last line ({found.torn_tail_bytes} bytes without a newline)")
    if found.bad_lines:
        problems.append(f"lines with the wrong number of fields: {found.bad_lines}")
    if found.t_host_nonincreasing:
        problems.append(f"host time is not strictly increasing at {found.t_host_nonincreasing} samples")
    if found.seq_resets:
        problems.append(f"sequence number went backwards or repeated {found.seq_resets} times")
    return problems


def _manifest_mismatches(entry: dict[str, Any], found: StreamSummary) -> list[str]:
    problems = []
    if entry.get("samples") != found.samples:
        problems.append(f"manifest says {entry.get('samples')} samples, file has {found.samples}")
    if entry.get("sha256") != found.sha256:
        problems.append("sha256 of the file differs from the manifest (file changed after recording)")
    return problems


def _gap_findings(entry: dict, found: StreamSummary, strict: bool, notes: list[str], name: str) -> list[str]:
    if not found.seq_gap_count:
        return []
    declared = (entry.get("seq_gaps") or {}).get("missing", 0)
    text = f"{found.seq_gap_count} sequence gap(s), {found.seq_missing} sample(s) missing"
    if found.seq_missing > declared:
        return [f"{text}; the manifest declares {declared}"]
    if strict:
        return [f"{text} (declared in the manifest; --strict)"]
    notes.append(f"{name}: {text}, declared in the manifest (device outage)")
    return []


@dataclass
class RepairReport:
    path: Path
    repaired: bool
    status: str
    cut: dict[str, dict[str, int]] = field(default_factory=dict)
    created: list[str] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    restored_manifest: bool = False

    def to_json(self) -> dict[str, Any]:
        return {"path": str(self.path), "repaired": self.repaired, "status": self.status, "cut": self.cut,
                "created": self.created, "removed": self.removed, "restored_manifest": self.restored_manifest}


def repair_session(path: Path | str) -> RepairReport:
    """Make a session left with status 'recording' (recorder killed) readable: cut torn trailing lines
    (kept in logs/repair-<stream>.cut, nothing is deleted), describe each stream from its file, and
    mark the session 'recovered'. In any session, first put a complete ``manifest.json.tmp`` in place
    when ``manifest.json`` is missing (refusing, with nothing changed, when it is not complete), then
    remove the temporary files interrupted writes left (``find_temporaries``). Nothing else of a
    finished session is touched. Holds the session lock, so it waits for a running midas command
    (whose output is still in temporaries) to finish first."""
    folder = Path(path)
    with session_lock(folder) if folder.is_dir() else contextlib.nullcontext():
        return _repair_locked(folder)


def _repair_locked(folder: Path) -> RepairReport:
    restored = _restore_manifest(folder)
    manifest = load_manifest(folder)
    removed = _remove_temporaries(folder)
    if manifest["status"] != "recording":
        return RepairReport(folder, repaired=False, status=manifest["status"], removed=removed,
                            restored_manifest=restored)
    report = RepairReport(folder, repaired=True, status="recovered", removed=removed, restored_manifest=restored)
    facts = stop_facts.read(folder)
    last_times = []
    for name, entry in manifest["streams"].items():
        spec = StreamSpec.from_manifest(name, entry)
        stream_path = Session(folder, manifest).stream_path(name)
        if not stream_path.exists():
            stream_path.parent.mkdir(parents=True, exist_ok=True)
            stream_path.write_text(spec.header_line(), encoding="utf-8")
            report.created.append(name)
        _cut_torn_tail(folder, name, stream_path, spec, report)
        found = summarize_stream(stream_path, spec)
        entry.update(found.manifest_fields())
        entry.update(facts["streams"].get(name, {}) if facts else {})
        entry["seq_gaps"]["note"] = "derived from the file by repair"
        if found.last_t_host_ns is not None:
            last_times.append(found.last_t_host_ns)
    stop_ns = max(last_times, default=manifest["start"]["host_ns"])
    manifest.update(
        status="recovered",
        stop={"utc": utc_iso(stop_ns), "host_ns": stop_ns},
        stop_reason=_recovered_reason(facts),
        repair={"utc": utc_iso(time.time_ns()), "midas_version": __version__, "cut": report.cut,
                "created_empty_streams": report.created},
    )
    write_manifest(folder, manifest)  # recovered first: the binary copies are an extra
    stop_facts.release(folder)
    add_binary_copies(folder, manifest)
    write_manifest(folder, manifest)
    return report


def _recovered_reason(facts: dict[str, Any] | None) -> str:
    """The stop reason of a repaired session: the recorder's own, when it kept one (``stop_facts``)."""
    if facts is None:
        return "the recorder stopped without finalising (crash or kill); recovered by `midas session repair`"
    return (f"{facts['stop_reason']} (status {facts['status']}; the recorder could not write the final manifest; "
            f"recovered by `midas session repair`)")


def _restore_manifest(folder: Path) -> bool:
    """Rename ``manifest.json.tmp`` to ``manifest.json`` when that is missing and the temporary holds a
    complete, valid manifest (a kill between its write and its rename); True if it did. A temporary
    that is not complete is the only trace of the manifest: refuse and leave it."""
    tmp = folder / MANIFEST_TMP
    if (folder / MANIFEST_NAME).is_file() or not tmp.is_file():
        return False
    try:
        read_manifest_file(tmp, folder)
    except SessionError as exc:
        raise SessionError(
            f"{folder} has no {MANIFEST_NAME} and its {MANIFEST_TMP} is not a complete manifest ({exc}); "
            f"nothing restored or deleted: the manifest was never written (delete the folder if it holds "
            f"nothing you need)") from exc
    os.replace(tmp, folder / MANIFEST_NAME)
    fsync_dir(folder)
    return True


def _remove_temporaries(folder: Path) -> list[str]:
    """Delete what ``find_temporaries`` finds (manifest.json is in place by now, so none is the only
    copy of anything midas cannot make again); return their relative paths."""
    removed = find_temporaries(folder)
    for rel in removed:
        (folder / rel).unlink(missing_ok=True)
    if removed:
        for parent in sorted({(folder / rel).parent for rel in removed}):
            fsync_dir(parent)
    return removed


def _cut_torn_tail(folder: Path, name: str, path: Path, spec: StreamSpec, report: RepairReport) -> None:
    data = read_regular_file(path)
    keep = complete_line_end(data, len(spec.columns))
    if keep == 0:
        keep_header = spec.header_line().encode()
        _save_cut(folder, name, data)
        _replace_bytes(path, keep_header)
        report.cut[name] = {"bytes": len(data), "lines": data.count(b"\n") + (not data.endswith(b"\n"))}
        return
    if keep == len(data):
        return
    cut = data[keep:]
    _save_cut(folder, name, cut)
    with open(path, "r+b") as fh:
        fh.truncate(keep)
        os.fsync(fh.fileno())
    report.cut[name] = {"bytes": len(cut), "lines": cut.count(b"\n") + (not cut.endswith(b"\n"))}


def _save_cut(folder: Path, name: str, cut: bytes) -> None:
    target = folder / "logs" / f"repair-{name}.cut"
    target.parent.mkdir(exist_ok=True)
    if target.exists():
        if target.read_bytes() == cut:  # an earlier repair saved these bytes, then stopped (e.g. disk full)
            return
        raise SessionError(f"{target} exists already: a previous repair was interrupted; inspect it first")
    _replace_bytes(target, cut)


def _replace_bytes(path: Path, data: bytes) -> None:
    """Write ``path`` through a temporary and a rename: a full disk leaves the old file (or none) as it
    was, never a half-written one."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
