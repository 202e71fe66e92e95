"""`midas record`: acquire a session with a live device-health display."""

from __future__ import annotations

import json
import logging
import signal
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer
from rich.live import Live
from rich.text import Text

from midas_cli import early_stop
from midas_cli.commands.common import STDERR_LOG, err, error_line, fail, positive
from midas_cli.config import RIG_ENV, config_path, default_priority, default_rig, default_sessions
from midas_cli.console import dashboard, is_interactive, recording_table, status_line
from midas_cli.devices.base import DeviceUrl, redact_url
from midas_cli.devices.lsl.outlet import exposure_note, lsl_config_file
from midas_cli.devices.rigconfig import DeviceConfig, RigConfig, load_rig
from midas_cli.errors import ConfigError, DeviceError, MidasError, SessionError
from midas_cli.record.foxglove_live import DEFAULT_ADDRESS as DEFAULT_FOXGLOVE, parse_address
from midas_cli.record.markers import check_stream_names, events_spec
from midas_cli.record.outcome import recording_problems, stream_outcomes
from midas_cli.record.priority import checked_priority
from midas_cli.record.pacing import run_until
from midas_cli.record.recorder import RecordPlan, Recorder
from midas_cli.record.status import RecorderSnapshot
from midas_cli.rig import simulated_rig
from midas_cli.session.writer import SessionMetadata

if TYPE_CHECKING:
    from midas_cli.commands.record_control import RemoteControl

PLAIN_EVERY_S = 2.0
READY_TIMEOUT_S = 15.0
MAX_SEED = 2**32 - 1
STOP_SIGNALS = {
    signal.SIGINT: ("complete", "stopped by the operator (Ctrl-C / SIGINT)"),
    signal.SIGTERM: ("interrupted", "terminated (SIGTERM)"),
    signal.SIGHUP: ("interrupted", "the terminal hung up (SIGHUP, e.g. SSH dropped)"),
}


def record(
    simulate: bool = typer.Option(False, "--simulate", help="Record from the built-in simulated rig."),
    rig: Optional[Path] = typer.Option(None, "--rig", help="Rig configuration file (TOML; default: $MIDAS_RIG or "
                                       "[record] rig in ~/.config/midas/config.toml).", dir_okay=False),
    device: list[str] = typer.Option([], "--device", help="Add or replace a device: NAME=URL (repeatable)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Folder that receives the session folder (default: "
                                       "$MIDAS_SESSIONS, [record] sessions in the config, else ./sessions)."),
    subject: Optional[str] = typer.Option(None, help="Subject id."),
    task: Optional[str] = typer.Option(None, help="Task name, e.g. suturing or peg-transfer."),
    trial: Optional[int] = typer.Option(None, help="Trial number."),
    platform: Optional[str] = typer.Option(None, help="Robot platform (default: the rig's)."),
    note: str = typer.Option("", "--note", help="Operator note stored in the manifest."),
    master_rate: Optional[float] = typer.Option(None, "--master-rate", callback=positive, help="Master rate in Hz (default: rig's)."),
    duration: Optional[float] = typer.Option(None, "--duration", callback=positive, help="Stop after this many seconds."),
    seed: int = typer.Option(0, "--seed", help="Seed for simulated devices."),
    no_tui: bool = typer.Option(False, "--no-tui", help="Plain status lines instead of the live screen."),
    status_json: bool = typer.Option(False, "--status-json", help="JSON lines on stdout: a status object a second, "
                                     "then a final {\"event\": \"stopped\", ...} with the session path."),
    queue_size: int = typer.Option(4096, "--queue-size", help="Bookkeeping messages a worker holds before merging "
                                   "them (rows are on disk first; nothing is dropped)."),
    lsl_out: bool = typer.Option(False, "--lsl-out", help="Also publish every stream live as an LSL outlet "
                                 "(labels, units, rate; timestamps = host times on the LSL clock). Outlets "
                                 "accept connections on every network interface: see README."),
    foxglove: bool = typer.Option(False, "--foxglove", help="Also serve the live streams to Foxglove over its "
                                  f"WebSocket protocol, on {DEFAULT_FOXGLOVE} (this machine only; see README)."),
    foxglove_address: Optional[str] = typer.Option(None, "--foxglove-address", metavar="HOST:PORT",
                                                   help="Where --foxglove listens (implies --foxglove)."),
    control: Optional[Path] = typer.Option(None, "--control", help="Control socket for `midas ctl` / `midas mark` "
                                           "(default: record-<pid>.sock in $XDG_RUNTIME_DIR/midas or /tmp/midas-<uid>)."),
    armed: bool = typer.Option(False, "--armed", help="Open the devices, then wait for `midas ctl start` (rows before "
                               "it are kept as warm-up; --duration counts from it)."),
    priority: Optional[str] = typer.Option(None, "--priority", metavar="normal|high", help="The device workers' "
                                           "scheduling priority: high = nice -10 where permitted (root, CAP_SYS_NICE "
                                           "or ulimit -e 30; else a warning), for a busy host (default: [record] "
                                           "priority in the config, else normal)."),
    live_model: Optional[Path] = typer.Option(None, "--live-model", metavar="RUN", help="Recognise gestures "
                                              "while recording with this causal model run (`train gestures "
                                              "--causal`): the stream gestures_live, shown live; refused "
                                              "before recording if the rig lacks a stream it needs "
                                              "(default: the rig file's [live] model)."),
) -> None:
    """Record a session from the rig's devices into a new session folder.

    One worker process per device, host-clock timestamps, crash-safe stream files. Stops on
    Ctrl-C, SIGTERM, SIGHUP, `midas ctl stop` or --duration; the session path is the last stdout
    line (with --status-json, the final JSON object's session_path). Markers (key m on the live
    screen, `midas mark TEXT`) go to the session's events stream.

    Example: midas record --simulate --duration 10 --out sessions --subject 1 --task suturing --trial 1
    """
    stop = _StopFlag()
    stop.install()  # first: from here on a stop signal ends the recording as documented, never a traceback
    try:
        _check_options(seed, master_rate, queue_size)
        live_address = foxglove_address if foxglove_address is not None else (DEFAULT_FOXGLOVE if foxglove else None)
        if live_address is not None:
            parse_address(live_address)  # a bad address: one error line before anything is created
        if lsl_out:
            from midas_cli.devices.lsl.device import import_pylsl

            import_pylsl()  # pylsl missing: one error line before anything is created
        priority = default_priority() if priority is None else checked_priority(priority, "--priority")
        rig_config = _choose_rig(simulate, rig, device)
        live_plan = None
        live_model = live_model if live_model is not None else rig_config.live_model  # the rig's [live] model
        if live_model is not None:
            from midas_cli.record.live_model import plan_live_model

            live_plan = plan_live_model(Path(live_model))  # a run that cannot run live: one line, nothing created
        plan = RecordPlan(_metadata(rig_config, subject, task, trial, platform, note, master_rate),
                          rig_config.device_urls(), default_sessions() if out is None else out, seed, queue_size,
                          rig_config.to_manifest(), lsl_out, foxglove=live_address, extra_streams=(events_spec(),),
                          priority=priority, live_model=live_plan)
        recorder = Recorder(plan)  # every URL checked, every stream layout known; nothing on disk yet
        check_stream_names(recorder.streams)
        _exit_if_stopped_before_start(stop)
        mode = "json" if status_json else ("tui" if is_interactive() and not no_tui else "plain")
        from midas_cli.commands.record_control import RemoteControl

        remote = RemoteControl(control, armed, stop)  # a socket in use: refused before anything is created
        try:
            _record(recorder, _Display(mode, stop), stop, duration, remote)
        finally:
            remote.close()  # the socket file goes on every exit path
    finally:
        stop.restore()


def _record(recorder: Recorder, display: "_Display", stop: "_StopFlag", duration: Optional[float],
            remote: "RemoteControl") -> None:
    """Create the session, show the devices opening, record until told, finalise, report. However it
    ends, once the session folder exists its path is stdout's last line (--status-json: the final
    object's session_path)."""
    try:
        _record_session(recorder, display, stop, duration, remote)
    except BaseException as exc:
        if recorder.writer is not None:  # the folder exists: a full disk, an error while finalising...
            display.after_error(recorder.path, exc)
        raise


def _record_session(recorder: Recorder, display: "_Display", stop: "_StopFlag", duration: Optional[float],
                    remote: "RemoteControl") -> None:
    should_stop = lambda: stop.asked or recorder.fatal_error is not None  # noqa: E731
    recorder.start()
    remote.attach(recorder)
    display.control_line = remote.control_line
    on_tick = remote.watching(display.update)
    ended = lambda: should_stop() or (not remote.armed and recorder.duration_reached(duration))  # noqa: E731
    with display, remote.keyboard(display.mode == "tui", display.message):
        display.message(f"midas: control socket {remote.path} (midas mark TEXT, midas ctl status|stop)")
        if recorder.plan.lsl_out:
            display.message(f"midas: --lsl-out: {exposure_note(lsl_config_file())}")
        if recorder.live is not None:
            display.message(f"midas: --foxglove: serving ws://{recorder.live.address} (Foxglove WebSocket)")
        ready = recorder.wait_ready(READY_TIMEOUT_S, ended, on_tick)
        priority_warning = recorder.priority_warning()
        if priority_warning:
            display.message(priority_warning)
        failed = {} if ended() else recorder.unopened()
        if failed:
            remote.finish("")
            manifest = recorder.stop("failed", f"could not open {', '.join(failed)} at the start")
            display.final(manifest, recorder.path)
            details = "; ".join(f"{name}: {error}" for name, error in failed.items())
            raise DeviceError(f"{details} (nothing recorded; the session folder is marked failed: {recorder.path})")
        if not ready and not ended():
            display.message(f"midas: warning: {', '.join(recorder.starting())} did not start within "
                            f"{READY_TIMEOUT_S:.0f} s; recording the others while they keep trying")
        duration = remote.wait_for_start(should_stop, on_tick, duration) if remote.armed else duration
        run_until(recorder, duration, should_stop, on_tick)
        display.update(recorder.snapshot(duration, stopping=True))
        status, reason = ("interrupted", recorder.fatal_error) if recorder.fatal_error else stop.outcome()
        if remote.prompt.text:  # typed on the live screen, never saved with Enter: say so, not silently drop it
            display.message(f"midas: warning: the marker being typed was not saved (the recording stopped "
                            f"before Enter): {remote.prompt.text}")
        manifest = recorder.stop(status, remote.finish(reason))
    display.final(manifest, recorder.path)
    if recorder.fatal_error:
        raise SessionError(f"{recorder.fatal_error} (session kept: {recorder.path})")


def _check_options(seed: int, master_rate: Optional[float], queue_size: int) -> None:
    """Refuse impossible values before anything is created (exit 2, one line)."""
    if not 0 <= seed <= MAX_SEED:
        raise ConfigError(f"--seed must be in 0..{MAX_SEED}, got {seed}")
    if master_rate is not None and master_rate > 1000:  # finite and > 0: checked by its option's callback
        raise ConfigError(f"--master-rate must be in (0, 1000] Hz, got {master_rate}")
    if queue_size < 16:
        raise ConfigError(f"--queue-size must be at least 16, got {queue_size}")


def _exit_if_stopped_before_start(stop: "_StopFlag") -> None:
    """A stop signal that came before the session existed: nothing to finalise, nothing created."""
    if stop.reason is not None:
        raise fail(f"stopped by {stop.reason.name} before the recording started; nothing was recorded",
                   128 + int(stop.reason))


def _choose_rig(simulate: bool, rig: Optional[Path], device: list[str]) -> RigConfig:
    if simulate and rig is not None:
        raise ConfigError("give either --simulate or --rig, not both")
    if not (simulate or rig):
        rig = default_rig()  # --device then adds to or replaces devices of the technician's rig
    if not (simulate or rig or device):
        raise ConfigError("nothing to record: give --simulate, --rig FILE or --device NAME=URL "
                          f"(or set {RIG_ENV} or [record] rig in {config_path()})")
    config = load_rig(rig) if rig else simulated_rig()
    if device and not (simulate or rig):
        config.devices.clear()
        config.name, config.platform, config.source = "command-line", "unknown", "--device"
        config.description = "devices given with --device"
    for item in device:
        name, sep, url = item.partition("=")
        if not sep or not name or not url:
            raise ConfigError(f"--device expects NAME=URL, got {redact_url(item)!r}")
        kind = DeviceUrl.parse(url).target.strip("/") if url.startswith("sim://") else name
        config.devices[name] = DeviceConfig(name, url, kind)  # checks the name (it names files)
    return config


def _metadata(rig: RigConfig, subject, task, trial, platform, note, master_rate) -> SessionMetadata:
    defaults = rig.metadata
    values = {"subject": subject if subject is not None else defaults.get("subject"),
              "task": task if task is not None else defaults.get("task"),
              "trial": trial if trial is not None else defaults.get("trial")}
    missing = [k for k, v in values.items() if v is None]
    if missing:
        raise ConfigError(f"missing --{', --'.join(missing)} (or [metadata] in the rig file)")
    return SessionMetadata(str(values["subject"]), values["task"], int(values["trial"]), platform or rig.platform,
                           note or defaults.get("operator_note", ""),
                           rig.master_rate_hz if master_rate is None else master_rate)


class _StopFlag:
    """Turns SIGINT/SIGTERM/SIGHUP into a stop request (the session is always finalised)."""

    def __init__(self) -> None:
        self.reason: Optional[signal.Signals] = None
        self.requested: Optional[str] = None  # a stop asked for over the control socket: its reason
        self.hung_up = False
        self._previous: dict = {}

    def install(self) -> None:
        """Stop signals become stop requests from here on; one the entry point already answered (its
        SystemExit lost on the way, ``midas_cli.early_stop``) ends the process now: 128 + its number."""
        for sig in STOP_SIGNALS:
            self._previous[sig] = signal.signal(sig, self._handle)
        if early_stop.received is not None:
            raise SystemExit(128 + early_stop.received)

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def _handle(self, signum: int, _frame) -> None:
        if self.reason is None:
            self.reason = signal.Signals(signum)
        if signum == signal.SIGHUP:
            self.hung_up = True

    def request(self, reason: str) -> None:
        """A stop asked for by `midas ctl stop`: ends the recording as Ctrl-C does."""
        if self.requested is None:
            self.requested = reason

    @property
    def asked(self) -> bool:
        return self.reason is not None or self.requested is not None

    def outcome(self) -> tuple[str, str]:
        if self.reason is None:
            return "complete", self.requested or "duration reached"
        return STOP_SIGNALS[self.reason]


class _Display:
    """Live TUI on a terminal, plain lines otherwise, or JSON lines; silent after a hang-up.

    With ``--status-json`` stdout carries JSON lines only: one ``{"event": "status", ...}`` a second
    and a final ``{"event": "stopped", ...}``; otherwise the session path is stdout's last line."""

    def __init__(self, mode: str, stop: _StopFlag) -> None:
        self.mode = mode
        self.stop = stop
        self._live: Optional[Live] = None
        self._last_plain = 0.0
        self._last_json = 0.0
        self.control_line = None  # a callable giving the live screen's marker line (markers, armed)
        self.path_shown = False  # the session path (or the final JSON object) is on stdout

    def __enter__(self) -> "_Display":
        if self.mode == "tui":
            self._log_level = STDERR_LOG.level
            STDERR_LOG.setLevel(logging.CRITICAL)  # the screen shows device errors; logs/midas.log keeps them
            self._live = Live(console=err, refresh_per_second=4, transient=False, redirect_stdout=False,
                              redirect_stderr=False)
            self._live.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self._live is not None:
            self._safely(lambda: self._live.__exit__(None, None, None))
            STDERR_LOG.setLevel(self._log_level)
            self._live = None

    def update(self, snapshot: RecorderSnapshot) -> None:
        if self.stop.hung_up:
            return
        now = time.monotonic()
        if self._live is not None:
            screen = dashboard(snapshot, None if self.control_line is None else self.control_line())
            self._safely(lambda: self._live.update(screen))
        elif self.mode == "json" and (now - self._last_json >= 1.0 or snapshot.stopping):
            self._last_json = now
            self._safely(lambda: _write_line(sys.stdout, json.dumps({"event": "status", **snapshot.to_json()},
                                                                    default=str)))
        elif self.mode == "plain" and (now - self._last_plain >= PLAIN_EVERY_S or snapshot.stopping):
            self._last_plain = now
            self._safely(lambda: _write_line(sys.stderr, status_line(snapshot)))

    def message(self, text: str) -> None:
        """A one-line notice on stderr (above the live screen in a terminal)."""
        if self.stop.hung_up:
            return
        if self._live is not None:
            self._safely(lambda: self._live.console.print(text, soft_wrap=True, markup=False))
        else:
            self._safely(lambda: error_line(text))

    def final(self, manifest: dict, path: Path) -> None:
        """The end-of-run summary on stderr, then the session path (or the final JSON object)."""
        if self.stop.hung_up:
            return
        self.path_shown = True
        self._safely(lambda: err.print(recording_table(manifest)))
        problems = recording_problems(manifest)
        if problems:
            self._safely(lambda: err.print(Text("problems: " + "; ".join(problems), style="bold yellow"),
                                           soft_wrap=True))
        if self.mode == "json":
            final = {"event": "stopped", "status": manifest["status"], "reason": manifest["stop_reason"],
                     "session_path": str(path), "session_id": manifest["session_id"],
                     "duration_s": _duration_s(manifest), "problems": problems,
                     "streams": stream_outcomes(manifest)}
            self._safely(lambda: _write_line(sys.stdout, json.dumps(final, default=str)))
        else:
            self._safely(lambda: _write_line(sys.stdout, str(path)))

    def after_error(self, path: Path, error: BaseException) -> None:
        """The session path (or a final JSON object with the status on disk and the error as reason)
        when the recording ended in an error before ``final`` showed it."""
        if self.stop.hung_up or self.path_shown:
            return
        self.path_shown = True
        if self.mode != "json":
            self._safely(lambda: _write_line(sys.stdout, str(path)))
            return
        reason = str(error) or type(error).__name__
        final = {"event": "stopped", "status": _status_on_disk(path), "reason": reason, "session_path": str(path),
                 "session_id": path.name, "duration_s": None, "problems": [reason], "streams": {}}
        self._safely(lambda: _write_line(sys.stdout, json.dumps(final, default=str)))

    def _safely(self, action) -> None:
        try:
            action()
        except OSError:  # terminal gone (EIO/EPIPE): keep recording, stop talking
            self.stop.hung_up = True


def _status_on_disk(path: Path) -> Optional[str]:
    """The status the session's manifest says, or None when it cannot be read."""
    from midas_cli.session.reader import Session

    try:
        return Session.open(path, allow_failed=True).status
    except (MidasError, OSError):
        return None


def _write_line(stream, text: str) -> None:
    stream.write(text + "\n")
    stream.flush()


def _duration_s(manifest: dict) -> Optional[float]:
    stop = (manifest.get("stop") or {}).get("host_ns")
    return None if stop is None else round((stop - manifest["start"]["host_ns"]) / 1e9, 3)
