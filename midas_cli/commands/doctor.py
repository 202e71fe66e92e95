"""`midas doctor`: what this machine offers midas (attach its --json output to bug reports)."""

from __future__ import annotations

import typer

from midas_cli import diagnostics
from midas_cli.commands.common import out, print_json
from midas_cli.commands.options import JSON_OPTION
from midas_cli.console import human_bytes
from midas_cli.devices.usbserial import AdapterReport


def doctor(
    obs_host: str = typer.Option("localhost", help="Where OBS's websocket server should be."),
    obs_port: int = typer.Option(4455, help="OBS websocket port."),
    as_json: bool = JSON_OPTION,
) -> None:
    """Report versions, serial ports, OBS reachability, GPU and free disk.

    Each USB serial adapter (/dev/ttyUSB*, /dev/ttyACM*) is listed with its driver, USB ids and latency
    timer; an FTDI timer above 1 ms is set to 1 ms where permitted, else the line says how (a udev rule).
    OBS settings that a killed `midas record` left changed (its saved copy under
    $XDG_STATE_HOME/midas/) are put back.

    Example: midas doctor --json > doctor.json
    """
    facts = diagnostics.collect(obs_host, obs_port)
    facts["obs_saved_settings"] = diagnostics.restore_obs_settings()
    if as_json:
        print_json(facts)
        return
    out.print(f"midas {facts['midas']}  python {facts['python']}  {facts['platform']}", markup=False)
    for name, version in facts["packages"].items():
        out.print(f"  {name:24} {version or 'NOT INSTALLED'}", markup=False)
    for name, where in facts["tools"].items():
        out.print(f"  {name:24} {where or 'not found'}", markup=False)
    ports = facts["serial_ports"]
    out.print(f"serial ports: {', '.join(p['device'] for p in ports) if ports else 'none'}", markup=False)
    if not facts["usb_serial"]:
        out.print("USB serial adapters: none", markup=False)
    for adapter in facts["usb_serial"]:
        out.print(f"USB serial adapter {AdapterReport(**adapter).summary()}", markup=False, soft_wrap=True)
    out.print(_priority_line(facts["high_priority"]), markup=False, soft_wrap=True)
    obs = facts["obs_websocket"]
    out.print(f"OBS websocket {obs['address']}: {'reachable' if obs['reachable'] else 'unreachable'}", markup=False)
    for saved in facts["obs_saved_settings"]:
        out.print(_saved_settings_line(saved), markup=False, soft_wrap=True)
    gpu = facts["gpu"]
    if not gpu.get("torch"):
        out.print("PyTorch: not installed (recording needs none; train, extract image-features and the calibration MLP "
                  "do: pip install 'midas-cli[train]')", markup=False)
    out.print(f"GPU: {', '.join(gpu['devices']) if gpu.get('cuda') else 'none (CPU only)'}", markup=False)
    out.print(f"disk free here: {human_bytes(facts['disk_free_bytes'])}", markup=False)


def _priority_line(priority: dict) -> str:
    """Whether `record --priority high` may lower the workers' nice value, and how to allow it if not."""
    verdict = f"permitted ({priority['by']})" if priority["permitted"] else f"not permitted; {priority['how']}"
    return f"record --priority high (nice -10): {verdict}"


def _saved_settings_line(saved: dict) -> str:
    if saved["status"] == "restored":
        return f"OBS settings: {saved['message']}"
    if saved["status"] == "in use":
        return (f"OBS settings: {saved['file']} belongs to a running midas (pid {saved['owner_pid']}); it puts "
                f"them back when it stops")
    return (f"OBS settings: NOT restored from {saved['file']} ({saved['error']}); start OBS, export its password "
            f"and run `midas doctor` again")
