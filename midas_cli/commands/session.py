"""`midas session info|list|verify|repair`: inspect and check session folders."""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Any, Optional

import typer
from rich.table import Table

from midas_cli.commands.common import err, out, print_json
from midas_cli.commands.options import JSON_OPTION, SESSION_ARG
from midas_cli.console import clock_text
from midas_cli.devices.base import redact_url
from midas_cli.errors import ConfigError, MidasError, SessionError
from midas_cli.session.manifest import STATUSES
from midas_cli.session.reader import Session, find_sessions
from midas_cli.session.summary import summarize_session

app = typer.Typer(help="Inspect, list, verify and repair session folders.", no_args_is_help=True)



def _fmt(value: Any, spec: str = "") -> str:
    return "—" if value is None else format(value, spec)


@app.command()
def info(path: Path = SESSION_ARG, as_json: bool = JSON_OPTION) -> None:
    """Summarise one session: metadata, status, devices and stream statistics.

    Metadata, status, duration, devices and per-stream rates, counts, gaps, and the first and last
    sample's host time in seconds from the session start (--json: also in host ns).

    Example: midas session info sessions/suturing_S1_T1_20260101T120000Z
    """
    summary = summarize_session(Session.open(path, allow_failed=True), clock_fits=True)
    for device in summary["devices"].values():  # a manifest from an older midas may hold a URL's password
        device["url"] = redact_url(device["url"]) if isinstance(device["url"], str) else device["url"]
    if as_json:
        print_json(summary)
        return
    duration = summary["duration_s"]
    out.print(f"[bold]{summary['session_id']}[/]  status [bold]{summary['status']}[/]"
              f"  ({summary['stop_reason'] or 'not stopped'})")
    out.print(f"task {summary['task']}  subject {summary['subject']}  trial {summary['trial']}  "
              f"platform {summary['platform']}  started {summary['start_utc']}  "
              f"duration {clock_text(duration) if duration is not None else '—'}")
    if summary["operator_note"]:
        out.print(f"note: {summary['operator_note']}", markup=False)
    table = Table("stream", "device", "nominal Hz", "measured Hz", "samples", "gaps", "missing", "dropped",
                  "corrupt", "p99 latency ms", "first s", "last s", header_style="bold")
    for name, s in summary["streams"].items():
        table.add_row(name, s["device"], _fmt(s["nominal_rate_hz"], "g"), _fmt(s["measured_rate_hz"], ".2f"),
                      _fmt(s["samples"]), _fmt(s["gaps"]), _fmt(s["missing"]), _fmt(s["dropped"]),
                      _fmt(s["corrupt"]), _fmt(s["latency_p99_ms"]), _fmt(s["first_s"], ".3f"),
                      _fmt(s["last_s"], ".3f"))
    out.print(table)
    for name, s in summary["streams"].items():
        fit = s["clock_fit"]
        if fit and fit.get("drift_ppm") is not None:
            out.print(f"clock {name}: host stamps vs {fit['clock']}: drift {_fmt(fit['drift_ppm'], '.1f')} ppm, "
                      f"jitter sd {_fmt(fit['jitter_sd_ms'], '.3f')} ms, p99 {_fmt(fit['jitter_p99_ms'], '.3f')} ms "
                      f"({_fmt(fit['segments'])} segment(s); midas align)", markup=False)
    for name, d in summary["devices"].items():
        out.print(f"device {name}: {d['kind']} {d['url']}  serial {d['serial'] or '—'}  "
                  f"reconnects {_fmt(d['reconnects'])}{_priority_text(d['priority'])}", markup=False)


def _priority_text(priority: Optional[dict[str, Any]]) -> str:
    """The worker's priority as `record --priority` left it ('' when the manifest has none)."""
    if not priority:
        return ""
    refused = " (high asked, not permitted)" if priority.get("asked") == "high" and priority.get("got") != "high" else ""
    return f"  priority {priority.get('got')}, nice {_fmt(priority.get('nice'))}{refused}"


@app.command("list")
def list_sessions(
    root: Optional[Path] = typer.Argument(None, help="Folder to search (default: $MIDAS_SESSIONS, [record] "
                                          "sessions in the config, else ./sessions)."),
    task: Optional[str] = typer.Option(None, help="Only sessions of this task."),
    subject: Optional[str] = typer.Option(None, help="Only sessions of this subject."),
    platform: Optional[str] = typer.Option(None, help="Only sessions on this platform."),
    status: Optional[str] = typer.Option(
        None, help="Only sessions with this status; a comma list for several (complete,interrupted,recovered)."),
    show_all: bool = typer.Option(
        False, "--all", help="Include recordings that failed to start (status 'failed'; hidden otherwise)."),
    latest: bool = typer.Option(
        False, "--latest", help="Only the newest session by start time, recording or interrupted included "
        "(failed ones with --all): its path (--json: path, status, start time, id); exit 4 if there is none."),
    paths: bool = typer.Option(False, "--paths", help="Print one session path per line instead of a table."),
    max_depth: int = typer.Option(3, "--max-depth", min=1, help="Folder levels under ROOT searched."),
    as_json: bool = JSON_OPTION,
) -> None:
    """Tabulate many sessions for scripts.

    Unreadable folders are reported on stderr and skipped (exit 4, except with --latest once a
    session is found). Recordings that failed to start are hidden unless --all (or --status
    failed); stderr says how many.

    Example: midas session list sessions --task suturing --json | jq -r '.[].path'

    Example (the session an SSH drop hid): path=$(midas session list sessions --latest)
    """
    if paths and as_json:
        raise ConfigError("give --paths or --json, not both")
    if root is None:
        from midas_cli.config import default_sessions

        root = default_sessions()
    statuses = _status_filter(status)
    wanted = {"task": task, "subject": subject, "platform": platform}
    rows, unreadable, hidden = [], 0, 0
    for folder in find_sessions(root, max_depth):
        try:
            session = Session.open(folder, allow_failed=True)
            summary = summarize_session(session)
        except MidasError as exc:  # one bad folder must not hide the others
            err.print(f"midas: skipping {folder}: {exc}", markup=False)
            unreadable += 1
            continue
        if not all(v is None or str(summary.get(k)) == v for k, v in wanted.items()):
            continue
        if statuses is not None and summary["status"] not in statuses:
            continue
        if summary["status"] == "failed" and statuses is None and not show_all:
            hidden += 1
            continue
        start_ns = session.manifest["start"].get("host_ns")
        summary["start_host_ns"] = start_ns if isinstance(start_ns, int) else None
        rows.append(summary)
    rows.sort(key=lambda r: _natural_key(r["path"]))
    if hidden:
        err.print(f"{hidden} failed session(s) hidden (recordings that never started; --all lists them)")
    if latest:
        filtered = any(v is not None for v in (task, subject, platform, status))
        _print_latest(root, rows, as_json, filtered, hidden)
        return
    if as_json:
        print_json([{k: v for k, v in r.items() if k != "devices"} for r in rows])
    elif paths:
        sys.stdout.write("".join(r["path"] + "\n" for r in rows))
    else:
        _print_session_table(rows)
    if unreadable:
        raise typer.Exit(4)


def _natural_key(text: str) -> list[Any]:
    """Sort key in which digit runs compare as numbers: T2 before T10."""
    return [(0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", text) if part]


def _status_filter(status: Optional[str]) -> Optional[set[str]]:
    if status is None:
        return None
    chosen = {s.strip() for s in status.split(",") if s.strip()}
    unknown = sorted(chosen - set(STATUSES))
    if unknown or not chosen:
        raise ConfigError(f"unknown status {', '.join(unknown) or repr(status)} (statuses: {', '.join(STATUSES)})")
    return chosen


def _print_latest(root: Path, rows: list[dict[str, Any]], as_json: bool, filtered: bool, hidden: int) -> None:
    """The newest session by the manifest's start time (host clock); ties go to the later folder name."""
    if not rows:
        why = [text for text, flag in (("matching the filters", filtered),
                                       (f"{hidden} failed one(s) hidden: --all lists them", hidden)) if flag]
        raise SessionError(f"no session under {root}" + (f" ({'; '.join(why)})" if why else ""))
    newest = max(rows, key=lambda r: (r["start_host_ns"] is not None, r["start_host_ns"] or 0, r["path"]))
    if as_json:
        print_json({"path": newest["path"], "status": newest["status"], "start_utc": newest["start_utc"],
                    "start_host_ns": newest["start_host_ns"], "session_id": newest["session_id"]})
    else:
        sys.stdout.write(newest["path"] + "\n")


def _print_session_table(rows: list[dict[str, Any]]) -> None:
    table = Table("session", "task", "subject", "trial", "platform", "status", "duration", "streams",
                  header_style="bold")
    for r in rows:
        duration = r["duration_s"]
        table.add_row(r["session_id"], r["task"], str(r["subject"]), str(r["trial"]), r["platform"], r["status"],
                      clock_text(duration) if duration is not None else "—", ",".join(r["streams"]))
    out.print(table)
    err.print(f"{len(rows)} session(s)")


@app.command()
def verify(
    paths: list[Path] = typer.Argument(..., help="Session folder(s)."),
    strict: bool = typer.Option(False, "--strict", help="Treat declared sequence gaps (outages) as problems."),
    as_json: bool = JSON_OPTION,
) -> None:
    """Check a session's files against its manifest; exit 4 if anything is wrong.

    Check the manifest against the files (counts, sha256, whole lines, every value against its
    column's type and range, monotonic host time, sequence gaps); exit 4 if anything is wrong.

    Example: midas session verify sessions/*/
    """
    from midas_cli.session.integrity import verify_session  # numpy and the stream parsers: only here

    reports = [verify_session(p, strict=strict) for p in paths]
    if as_json:
        print_json([r.to_json() for r in reports])
    else:
        for report in reports:
            verdict = "[green]OK[/]" if report.ok else f"[red]{len(report.problems)} problem(s)[/]"
            out.print(f"{report.path}: {verdict}")
            for problem in report.problems:
                out.print(f"  problem: {problem}", markup=False)
            for note in report.notes:
                out.print(f"  note: {note}", markup=False)
    if not all(r.ok for r in reports):
        raise typer.Exit(4)


@app.command()
def repair(paths: list[Path] = typer.Argument(..., help="Session folder(s)."), as_json: bool = JSON_OPTION) -> None:
    """Make a crashed session readable and clear interrupted temporary files.

    Make a session left by a crash (status 'recording') readable: cut torn last lines (kept in
    logs/repair-<stream>.cut), recount every stream, mark it 'recovered'. In any session, remove
    the temporary files an interrupted write left (*.tmp), and put a complete manifest.json.tmp in
    place when manifest.json is missing.

    Example: midas session repair sessions/suturing_S1_T1_20260101T120000Z && midas session verify $_
    """
    from midas_cli.session.integrity import repair_session

    reports = [repair_session(p) for p in paths]
    if as_json:
        print_json([r.to_json() for r in reports])
        return
    for report in reports:
        if report.restored_manifest:
            out.print(f"{report.path}: manifest.json was missing; put the complete manifest.json.tmp in its place",
                      markup=False)
        if not report.repaired:
            done = f"removed {len(report.removed)} temporary file(s)" if report.removed else "nothing to repair"
            out.print(f"{report.path}: status {report.status!r}, {done}", markup=False)
        else:
            cut = ", ".join(f"{s}: {c['lines']} partial line(s), {c['bytes']} bytes" for s, c in report.cut.items())
            out.print(f"{report.path}: recovered; cut {cut or 'nothing'}", markup=False)
            for name in report.created:
                out.print(f"  stream {name} had no file; created it empty", markup=False)
        for rel in report.removed:
            out.print(f"  removed temporary file {rel}", markup=False)
