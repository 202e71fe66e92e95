"""`midas config`: the defaults a technician set once, and where each comes from."""

from __future__ import annotations

from midas_cli.commands.common import out, print_json
from midas_cli.commands.options import JSON_OPTION


def config(as_json: bool = JSON_OPTION) -> None:
    """Show the defaults in use (rig, sessions, SLURM) and where each comes from.

    Precedence: the command's flag, then MIDAS_RIG / MIDAS_SESSIONS, then the config file
    ($MIDAS_CONFIG, else $XDG_CONFIG_HOME/midas/config.toml, else ~/.config/midas/config.toml),
    then the built-in default. A config file with an unknown section or key is an error (exit 2).

    Example: MIDAS_SESSIONS=/data/sessions midas config --json
    """
    from midas_cli.config import describe_defaults

    rows = describe_defaults()
    if as_json:
        print_json(rows)
        return
    file_row = rows["config_file"]
    out.print(f"config file: {file_row['path']}" + ("" if file_row["exists"] else " (none)"), markup=False)
    for key in ("rig", "sessions"):
        value = rows[key]["value"]
        out.print(f"{key}: {value if value is not None else '—'}  ({rows[key]['source']})", markup=False)
    slurm = rows["slurm"]
    out.print("slurm: " + (", ".join(f"{k}={v}" for k, v in slurm.items()) if slurm else "—"), markup=False)
