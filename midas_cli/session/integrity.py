"""`verify` (the manifest against the files) and `repair` (a session left behind by a crash)."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from midas_cli import __version__
from midas_cli.errors import SessionError
from midas_cli.session.columnar import add_binary_copies, copy_differences
from midas_cli.session.manifest import load_manifest, write_manifest
from midas_cli.session.reader import Session
from midas_cli.session.schema import StreamSpec
from midas_cli.session.streamfile import StreamSummary, complete_line_end, summarize_stream
from midas_cli.session.writer import utc_iso

FINISHED = ("complete", "interrupted", "recovered")


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
    """Check every stream file against the manifest: presence, header, whole lines, sample count,
    sha256, strictly increasing host time, sequence gaps, and that its binary copy (if any) holds
    exactly what the CSV holds. Gaps the manifest declares (a device
    outage the recorder saw) are notes, or problems with ``strict``; undeclared gaps are problems."""
    session = Session.open(path)
    report = VerifyReport(session.path)
    if session.status not in FINISHED:
        report.problems.append(
            f"status is {session.status!r}: the recorder did not finish (run `midas session repair {session.path}`)"
        )
    for name in session.stream_names:
        _verify_stream(session, name, report, strict)
    return report


def _verify_stream(session: Session, name: str, report: VerifyReport, strict: bool) -> None:
    entry = session.manifest["streams"][name]
    path = session.stream_path(name)
    if not path.is_file():
        report.problems.append(f"{name}: file {entry['file']} is missing")
        return
    spec = session.stream_spec(name)
    found = summarize_stream(path, spec)
    report.streams[name] = {"samples": found.samples, "seq_missing": found.seq_missing,
                            "measured_rate_hz": found.measured_rate_hz}
    problems = _file_problems(found)
    if session.status in FINISHED:
        problems += _manifest_mismatches(entry, found)
    problems += _gap_findings(entry, found, strict, report.notes, name)
    if not problems:
        problems += copy_differences(session.path, name, entry)
    report.problems.extend(f"{name}: {p}" for p in problems)


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

    def to_json(self) -> dict[str, Any]:
        return {"path": str(self.path), "repaired": self.repaired, "status": self.status, "cut": self.cut,
                "created": self.created}


def repair_session(path: Path | str) -> RepairReport:
    """Make a session left with status 'recording' (recorder killed) readable: cut torn trailing lines
    (kept in logs/repair-<stream>.cut, nothing is deleted), describe each stream from its file, and
    mark the session 'recovered'. A finished session is left untouched."""
    folder = Path(path)
    manifest = load_manifest(folder)
    if manifest["status"] != "recording":
        return RepairReport(folder, repaired=False, status=manifest["status"])
    report = RepairReport(folder, repaired=True, status="recovered")
    last_times = []
    for name, entry in manifest["streams"].items():
        spec = StreamSpec.from_manifest(name, entry)
        stream_path = Session(folder, manifest).stream_path(name)
        if not stream_path.is_file():
            stream_path.parent.mkdir(parents=True, exist_ok=True)
            stream_path.write_text(spec.header_line(), encoding="utf-8")
            report.created.append(name)
        _cut_torn_tail(folder, name, stream_path, spec, report)
        found = summarize_stream(stream_path, spec)
        entry.update(found.manifest_fields())
        entry["seq_gaps"]["note"] = "derived from the file by repair"
        if found.last_t_host_ns is not None:
            last_times.append(found.last_t_host_ns)
    stop_ns = max(last_times, default=manifest["start"]["host_ns"])
    manifest.update(
        status="recovered",
        stop={"utc": utc_iso(stop_ns), "host_ns": stop_ns},
        stop_reason="the recorder stopped without finalising (crash or kill); recovered by `midas session repair`",
        repair={"utc": utc_iso(time.time_ns()), "midas_version": __version__, "cut": report.cut,
                "created_empty_streams": report.created},
    )
    write_manifest(folder, manifest)  # recovered first: the binary copies are an extra
    add_binary_copies(folder, manifest)
    write_manifest(folder, manifest)
    return report


def _cut_torn_tail(folder: Path, name: str, path: Path, spec: StreamSpec, report: RepairReport) -> None:
    data = path.read_bytes()
    keep = complete_line_end(data, len(spec.columns))
    if keep == 0:
        keep_header = spec.header_line().encode()
        _save_cut(folder, name, data)
        path.write_bytes(keep_header)
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
        raise SessionError(f"{target} exists already: a previous repair was interrupted; inspect it first")
    target.write_bytes(cut)
