"""Terminal rendering helpers (the one library module besides commands/ that imports rich).

Pure functions of snapshots: the recorder never renders, renderers never touch devices.
"""

from __future__ import annotations

import os
import sys
from typing import Any

from rich.columns import Columns
from rich.console import Console, ConsoleOptions, Group, RenderResult
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from midas_cli.record.live_model import RECOGNITION_KIND
from midas_cli.record.outcome import stream_outcomes
from midas_cli.record.status import DeviceStatus, GestureStatus, RecorderSnapshot, StreamStatus

STATE_STYLE = {"ok": "bold green", "degraded": "bold yellow", "lost": "bold red", "starting": "cyan", "opening": "cyan",
               "stopped": "dim"}
BAR_WIDTH = 8  # the pedal bars: narrow enough that pedals and EmHT sit side by side in 80 columns
STALE_PANEL_S = 1.0  # a panel whose last sample is older than this is marked stale


def stderr_console() -> Console:
    """Progress, live status and errors go to stderr so stdout stays clean for results. When stderr
    is not a terminal (a log file, a pipe, SSH without a pty) nothing is ever folded: one message is
    one line, and tables get room instead of the 80-column default."""
    if sys.stderr.isatty():
        return Console(stderr=True, highlight=False, no_color="NO_COLOR" in os.environ or None)
    return Console(stderr=True, highlight=False, width=200, soft_wrap=True,
                   no_color="NO_COLOR" in os.environ or None)


def stdout_console() -> Console:
    """Results. When stdout is a pipe or file, tables get room instead of the 80-column default."""
    if sys.stdout.isatty():
        return Console(highlight=False, no_color="NO_COLOR" in os.environ or None)
    return Console(highlight=False, width=200, soft_wrap=True, no_color="NO_COLOR" in os.environ or None)


def is_interactive() -> bool:
    return sys.stdout.isatty() and sys.stderr.isatty() and os.environ.get("TERM", "") != "dumb"


def human_bytes(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if abs(n) < 1024 or unit == "TB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.1f} TB"


def clock_text(seconds: float) -> str:
    seconds = max(0, int(seconds))
    return f"{seconds // 3600:02d}:{seconds % 3600 // 60:02d}:{seconds % 60:02d}"


def _rate_text(stream: StreamStatus) -> str:
    if stream.nominal_rate_hz is None:
        return "events"
    measured = "—" if stream.measured_rate_hz is None else f"{stream.measured_rate_hz:.1f}"
    return f"{measured} / {stream.nominal_rate_hz:g}"


def _nominal_text(stream: StreamStatus) -> str:
    return "events" if stream.nominal_rate_hz is None else f"{stream.nominal_rate_hz:g}Hz"


def _age_text(age: float | None) -> str:
    if age is None:
        return "—"
    return f"{age * 1000:.0f} ms" if age < 10 else f"{age:.0f} s"


def dashboard(snapshot: RecorderSnapshot, control: Text | None = None) -> Group:
    """The live TUI, laid out for an 80x24 SSH terminal (the simulated rig's every pedal included): a
    one-line header, the session's path (from the start; shortened on the left to fit), ``control``
    (markers: ``control_line``; near the top, so a short terminal never crops it), device health,
    then the pedal bars and EmHT positions side by side."""
    top: list[Any] = [_header(snapshot), _PathLine(snapshot.session_path)]
    if control is not None:
        top.append(control)
    if snapshot.recognising:
        top.append(gesture_line(snapshot.gesture))
    errors = _device_errors(snapshot)
    return Group(*top, _device_table(snapshot), *([errors] if errors.plain else []),
                 Columns(_live_panels(snapshot)))


class _PathLine:
    """``session <path>`` on one line: a path too long for the terminal loses its start, not its end
    (the session's own folder name)."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        room = max(options.max_width - len("session "), 1)
        path = self.path if len(self.path) <= room else "…" + self.path[-(room - 1):]
        yield Text.assemble(("session ", "dim"), path, no_wrap=True, overflow="crop")


def _header(snapshot: RecorderSnapshot) -> Text:
    total = "" if snapshot.duration_s is None else f"/{clock_text(snapshot.duration_s)}"
    state = "  [stopping…]" if snapshot.stopping else "  Ctrl-C stops"
    return Text.assemble(
        ("● REC ", "bold red"), f"elapsed {clock_text(snapshot.elapsed_s)}{total}",
        f"  disk free {human_bytes(snapshot.disk_free_bytes)}",
        f"  {human_bytes(snapshot.write_rate_bps)}/s", (state, "dim"), no_wrap=True, overflow="ellipsis",
    )


def _device_table(snapshot: RecorderSnapshot) -> Table:
    # rate: measured / nominal; age: last sample. No outer edge: two lines more for the pedals at 80x24
    table = Table(expand=False, header_style="bold", pad_edge=False, show_edge=False)
    for column in ("device", "state", "rate Hz", "samples", "age", "drop", "corr", "miss", "reconn"):
        table.add_column(column, justify="left" if column in ("device", "state") else "right", no_wrap=True,
                         min_width=len(column))

    for device in snapshot.devices:
        for stream in device.streams:
            table.add_row(
                _row_label(device, stream),
                Text(device.state, STATE_STYLE.get(device.state, "")), _rate_text(stream), str(stream.samples),
                _age_text(stream.last_age_s), str(stream.dropped), str(stream.corrupt), str(stream.seq_missing),
                str(device.reconnects),
            )
    return table


def _row_label(device: DeviceStatus, stream: StreamStatus) -> str:
    """``device/stream``, or the one name where that says it all (the live recognition: its stream)."""
    if stream.name == device.name or device.kind == RECOGNITION_KIND:
        return stream.name
    return f"{device.name}/{stream.name}"


def _device_errors(snapshot: RecorderSnapshot) -> Text:
    """Last error of every device that is not healthy (red), then each device's last warning (yellow),
    one line each."""
    lines = [d.last_error for d in snapshot.devices if d.last_error and d.state != "ok"]
    text = Text("\n".join(lines), "red")
    for device in snapshot.devices:
        if device.warning:
            text.append(("\n" if text.plain else "") + f"{device.name}: {device.warning}", "yellow")
    return text


def _live_panels(snapshot: RecorderSnapshot) -> list[Panel]:
    """Pedal bars and EmHT positions. Values that are not live (the device is not ok, or its last
    sample is older than STALE_PANEL_S) are dimmed and the panel's title says how old they are."""
    panels = []
    for device in snapshot.devices:
        for stream in device.streams:
            if not stream.latest or device.kind not in ("fps", "emht"):
                continue
            stale = _staleness(device, stream)
            if device.kind == "fps":
                body, title = _pedal_bars(stream.latest, device.labels, bool(stale)), f"{device.name}: pedals (V, ● pressed)"
            else:
                body, title = _emht_positions(stream.latest, device.labels), f"{device.name}: positions (mm)"
            panels.append(Panel(body, title=title + (f" [{stale}]" if stale else ""), expand=False,
                                border_style="red" if stale else "", style="dim" if stale else ""))
    return panels


def _staleness(device: DeviceStatus, stream: StreamStatus) -> str:
    """'' for live values, else why they are not (e.g. 'STALE 3.2 s, lost')."""
    age = stream.last_age_s
    if device.state in ("ok", "degraded") and age is not None and age <= STALE_PANEL_S:
        return ""
    age_text = "" if age is None else f" {age:.1f} s"
    state = "" if device.state in ("ok", "degraded") else f", {device.state}"
    return f"STALE{age_text}{state}"


def _pedal_bars(latest: dict[str, Any], labels: dict[str, str], stale: bool = False) -> Table:
    table = Table.grid(padding=(0, 1))
    table.add_column(no_wrap=True)
    table.add_column(no_wrap=True, min_width=BAR_WIDTH)
    table.add_column(no_wrap=True, justify="right")
    table.add_column(no_wrap=True, min_width=1)
    from midas_cli.devices.pedals import adc_to_volts  # numpy: here, so `midas session ...` never loads it

    channel = 1
    while f"ch{channel}_adc" in latest:
        volts = float(adc_to_volts(latest[f"ch{channel}_adc"]))
        filled = int(round(volts / 5.0 * BAR_WIDTH))
        pressed = latest.get(f"ch{channel}_pressed") == 1 and not stale
        bar = Text("█" * filled + "·" * (BAR_WIDTH - filled), "bold magenta" if pressed else "magenta")
        table.add_row(labels.get(str(channel), f"P{channel}"), bar, f"{volts:4.2f}V", Text("●" if pressed else "", "bold"))
        channel += 1
    return table


def _emht_positions(latest: dict[str, Any], labels: dict[str, str]) -> Table:
    table = Table("", "x", "y", "z", box=None, padding=(0, 1), pad_edge=False)
    sensor = 1
    while f"s{sensor}_x_mm" in latest:
        values = [latest[f"s{sensor}_{a}_mm"] for a in "xyz"]
        name = labels.get(str(sensor))
        table.add_row(f"s{sensor}" + (f" {name}" if name else ""),
                      *("—" if v is None or v != v else f"{v:6.1f}" for v in values))
        sensor += 1
    return table


def gesture_line(gesture: GestureStatus | None) -> Text:
    """`record --live-model`: the current gesture, its probability, how long it has lasted and the
    recognition latency (decision time - frame time of the last frame); dimmed once it is stale."""
    if gesture is None:
        return Text("gesture: waiting for the first frame", "dim")
    stale = gesture.age_s > STALE_PANEL_S
    return Text.assemble(("gesture ", "dim"), (gesture.label, "dim" if stale else "bold cyan"),
                         f"  p {gesture.probability:.2f}  for {gesture.duration_s:.1f} s",
                         f"  latency {gesture.latency_ms:.0f} ms", (f"  STALE {gesture.age_s:.1f} s" if stale else "", "red"),
                         no_wrap=True, overflow="ellipsis")


def status_line(snapshot: RecorderSnapshot) -> str:
    """One plain line for logs and non-TTY output."""
    parts = [f"[{clock_text(snapshot.elapsed_s)}]"]
    for device in snapshot.devices:
        for stream in device.streams:
            rate = "-" if stream.measured_rate_hz is None else f"{stream.measured_rate_hz:.1f}"
            extra = "".join(f" {k}={v}" for k, v in (("dropped", stream.dropped), ("corrupt", stream.corrupt),
                                                     ("missing", stream.seq_missing),
                                                     ("reconnects", device.reconnects)) if v)
            parts.append(f"{stream.name} {device.state} {rate}/{_nominal_text(stream)} n={stream.samples}{extra}")
    if snapshot.gesture is not None:
        g = snapshot.gesture
        parts.append(f"gesture {g.label} p={g.probability:.2f} for {g.duration_s:.1f}s latency {g.latency_ms:.0f}ms")
    parts.append(f"disk {human_bytes(snapshot.disk_free_bytes)} free")
    return " | ".join(parts)



def control_line(prompt: str | None, markers: int, last_marker: str | None, armed_waiting: bool,
                 keys: bool) -> Text:
    """The live screen's marker line: the marker being typed, or how to add one and the last one; while
    armed, that the recording waits for `midas ctl start`."""
    if prompt is not None:
        return Text.assemble(("marker: ", "bold"), prompt, ("▌", "bold"), ("   Enter saves, Esc cancels", "dim"))
    parts: list[Any] = []
    if armed_waiting:
        parts.append(("ARMED: devices open, waiting for `midas ctl start`   ", "bold yellow"))
    if keys:
        parts.append(("m: add a marker", "dim"))
    if markers:
        parts.append((f"   markers {markers}, last: {(last_marker or '')[:40]}", "dim"))
    return Text.assemble(*parts)


def recording_table(manifest: dict) -> Table:
    """The end of `midas record`: per stream what was recorded and what went wrong (missing in outages / unexplained,
    dropped, corrupt, reconnects of its device)."""
    table = Table("stream", "samples", "measured Hz", "missing (outage / other)", "dropped", "corrupt",
                  "reconnects", "p99 latency ms",
                  title=f"{manifest['session_id']}: {manifest['status']} ({manifest['stop_reason']})",
                  header_style="bold")
    for name, o in stream_outcomes(manifest).items():
        rate = o["measured_rate_hz"]
        missing = f"{o['missing_outage']} / {o['missing_unexplained']}" if o["missing"] else "0"
        rate_text = "events" if o["nominal_rate_hz"] is None else "—" if rate is None else f"{rate:.2f}"
        table.add_row(name, str(o["samples"]), rate_text,
                      Text(missing, "yellow" if o["missing"] else ""), str(o["dropped"]), str(o["corrupt"]),
                      str(o["reconnects"]), "—" if o["p99_latency_ms"] is None else str(o["p99_latency_ms"]))
    return table
