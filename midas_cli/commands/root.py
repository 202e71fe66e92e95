"""What `midas` answers before typer is imported: `--version`, and the root help from a static table.

`midas --version` and `midas --help` (or plain `midas`) used to build the whole CLI, importing every
command's module (scipy, pandas, torch...): seconds for one line. Here they cost the interpreter's own
start-up. The root help is drawn to look like typer's (same panels, wrapping and colours), from
``REGISTRY``, the one table of commands (commands/main.py registers them from it); tests/commands/test_startup.py
holds its summaries and ``ROOT_HELP`` to the real commands' help and the drawing to typer's own. Only
stdlib imports here: this module is on the fast path.
"""

from __future__ import annotations

import os
import sys

from midas_cli import __version__

class Command:
    """One entry of the command registry: everything midas needs to know about a top-level command.

    ``module`` (under midas_cli.commands) and ``attribute`` name the typer command function or group
    (``kind`` "command" or "group"); ``summary`` is the first paragraph of its help, as `midas --help`
    lists it (tests/commands/test_startup.py holds it to the real help). An entry with ``renamed_to`` is an old
    spelling kept for a release: hidden from help and completion, and running it warns on stderr.
    """

    __slots__ = ("name", "module", "attribute", "kind", "summary", "renamed_to")

    def __init__(self, name: str, module: str, attribute: str, kind: str, summary: str = "",
                 renamed_to: str = "") -> None:
        self.name, self.module, self.attribute, self.kind = name, module, attribute, kind
        self.summary, self.renamed_to = summary, renamed_to

    @property
    def hidden(self) -> bool:
        return bool(self.renamed_to)


# In the order of the tree (README, "Commands"): record and control it; inspect sessions and labels;
# derive and analyse; move data in and out; simulate hardware; the machine, the defaults, batch runs.
REGISTRY: tuple[Command, ...] = (
    Command("record", "record", "record", "command",
            "Record a session from the rig's devices into a new session folder."),
    Command("mark", "control", "mark", "command", "Add a marker to the running recording's events stream."),
    Command("ctl", "control", "app", "group", "Remote control of a running recording (start, stop, status, mark)."),
    Command("session", "session", "app", "group", "Inspect, list, verify and repair session folders."),
    Command("labels", "labels", "app", "group", "Gesture taxonomies, annotation import/export and label statistics."),
    Command("plot", "plot", "plot", "command",
            "Draw a quick-look page of a session: every stream against session time."),
    Command("align", "align", "align", "command", "Align each session's streams onto its video frame clock."),
    Command("extract", "extract", "app", "group",
            "Derive data from recordings offline: hand keypoints, pedals, image features."),
    Command("calibrate", "calibrate", "app", "group", "Calibrate devices and write the results into a rig file."),
    Command("eval", "eval", "app", "group",
            "Validate sensing modalities against robot ground truth (paper tables)."),
    Command("train", "train", "app", "group", "Train and evaluate gesture-recognition models."),
    Command("export", "export", "export", "command",
            "Export sessions as MCAP (Foxglove), Parquet, XDF (LSL) and/or LeRobot datasets."),
    Command("replay", "replay", "replay", "command",
            "Play a session's streams back as live LSL outlets with their recorded timing."),
    Command("import", "import_cmd", "app", "group", "Import sessions from other formats."),
    Command("simulate", "simulate", "app", "group",
            "Synthetic recordings with known ground truth (no hardware needed)."),
    Command("emulate", "emulate", "app", "group", "Serve emulated serial devices on pseudo-terminals."),
    Command("rig", "rig", "app", "group", "Check or list a rig's devices before recording."),
    Command("doctor", "doctor", "doctor", "command", "Report versions, serial ports, OBS reachability, GPU and free disk."),
    Command("config", "config_cmd", "config", "command",
            "Show the defaults in use (rig, sessions, SLURM) and where each comes from."),
    Command("jobs", "jobs", "app", "group",
            "Follow batch runs (--executor local|slurm): each unit's state, log and error."),
    Command("ground-truth", "ground_truth", "app", "group", renamed_to="midas extract pedals"),
    Command("features", "features", "app", "group", renamed_to="midas extract image-features"),
)
COMMANDS: dict[str, Command] = {command.name: command for command in REGISTRY}


def listed() -> list[Command]:
    """The commands `midas --help` lists, as typer orders them: commands, then groups, each in registry order."""
    shown = [command for command in REGISTRY if not command.hidden]
    return [c for c in shown if c.kind == "command"] + [c for c in shown if c.kind == "group"]


# `midas --help`'s description (typer's app callback takes it as its help).
ROOT_HELP = """midas: record and analyse multimodal data in robot-assisted surgery (MiDAS).

Every command reads and writes self-describing session folders; results go to stdout,
progress and errors to stderr.

Exit codes: 0 ok, 1 internal, 2 usage, 3 device, 4 session/data."""

# (option names, short names, help) as typer shows the root options
ROOT_OPTIONS: tuple[tuple[str, str, str], ...] = (
    ("--debug", "", "Show tracebacks and debug logging."),
    ("--version", "", "Print the version."),
    ("--install-completion", "", "Install completion for the current shell."),
    ("--show-completion", "", "Show completion for the current shell, to copy it or customize the installation."),
    ("--help", "-h", "Show this message and exit."),
)

_HELP_FLAGS = {"--help", "-h"}
MIN_STATIC_WIDTH = 55  # narrower, rich squeezes typer's columns its own way: let typer draw it


def answer_without_typer(argv: list[str]) -> int | None:
    """Print the answer to `midas [--debug] --version|--help` (or bare `midas`) and return the exit
    status; None for anything else, which the typer app handles (a shell's completion request too)."""
    if any(name.endswith("_COMPLETE") for name in os.environ):  # `_MIDAS_COMPLETE=...`: typer's completion
        return None
    flags = set(argv) - {"--debug"}
    if flags == {"--version"}:
        sys.stdout.write(f"midas {__version__}\n")
        return 0
    width = terminal_width()
    if (not argv or (flags and flags <= _HELP_FLAGS)) and width >= MIN_STATIC_WIDTH:
        text = root_help(width, styled=_styled())
        sys.stdout.write(text if argv else text.removesuffix("\n"))  # bare `midas`: typer's no-args help, exit 2
        return 0 if argv else 2
    return None


def terminal_width() -> int:
    """The width rich (so typer) would draw at: $TERMINAL_WIDTH, $COLUMNS, the terminal's, else 80."""
    for name in ("TERMINAL_WIDTH", "COLUMNS"):
        value = os.environ.get(name, "")
        if value.isdigit() and int(value) > 0:
            return int(value)
    for stream in (sys.stdin, sys.stdout, sys.stderr):
        try:
            return os.get_terminal_size(stream.fileno()).columns or 80
        except (AttributeError, ValueError, OSError):
            continue
    return 80


def _styled() -> bool:
    env = os.environ
    if env.get("_TYPER_FORCE_DISABLE_TERMINAL"):
        return False
    if env.get("GITHUB_ACTIONS") or env.get("FORCE_COLOR") or env.get("PY_COLORS"):
        return True
    if env.get("TERM", "").lower() in ("dumb", "unknown"):
        return False
    try:
        return sys.stdout.isatty()
    except (AttributeError, ValueError):
        return False


def _wrap(text: str, width: int) -> list[str]:
    import textwrap

    return textwrap.wrap(text, max(width, 1), break_on_hyphens=False, break_long_words=True) or [""]


def root_help(width: int, styled: bool = False) -> str:
    """`midas --help` as typer draws it at ``width`` columns (with its ANSI styles when ``styled``)."""
    colour = styled and not os.environ.get("NO_COLOR")

    def sgr(text: str, code: str, colour_code: str = "") -> str:
        if not styled:
            return text
        codes = ";".join(c for c in (code, colour_code if colour else "") if c)
        return f"\x1b[{codes}m{text}\x1b[0m" if codes else text

    def padded(text: str, length: int) -> str:
        return text + " " * max(width - length, 0)

    lines = [sgr(" " * width, "1")]
    usage = "midas [OPTIONS] COMMAND [ARGS]..."
    lines.append(sgr(" ", "1") + sgr("Usage: ", "1", "33") + sgr(usage, "1")
                 + sgr(" " * max(width - 9 - len(usage), 0), "1") + sgr(" ", "1") if styled
                 else padded(f" Usage: {usage}", 8 + len(usage)))
    lines.append(sgr(" " * width, "1"))
    paragraphs = ROOT_HELP.split("\n\n")
    for index, paragraph in enumerate(paragraphs):
        for source_line in paragraph.split("\n"):
            wrapped = _wrap(source_line, width - 2)
            for i, line in enumerate(wrapped):
                if i < len(wrapped) - 1 and len(line) < width - 2:
                    line += " "  # rich keeps the space it broke at where it fits
                body = line if index == 0 or not styled else sgr(line, "2")
                lines.append(" " + body + " " * max(width - 1 - len(line), 0))
        lines.append(" " * width)

    def panel(title: str, rows: list[tuple[list[str], str]], lead: int) -> None:
        """rows: (styled cells of the ``lead`` columns before the help, help text)."""
        head = f"╭─ {title} "
        lines.append(sgr("╭─", "2") + sgr(f" {title} ", "2") + sgr("─" * max(width - len(head) - 2, 0), "2") + sgr("─╮", "2")
                     if styled else head + "─" * max(width - len(head) - 1, 0) + "╮")
        help_width = width - lead - 2
        for cells, help_text in rows:
            for i, line in enumerate(_wrap(help_text, help_width)):
                first = cells[0] if i == 0 else cells[1]
                lines.append(sgr("│", "2") + first + line + " " * max(help_width - len(line), 0) + " " + sgr("│", "2"))
        lines.append(sgr("╰" + "─" * max(width - 2, 0) + "╯", "2"))

    name_width = max(len(name) for name, _, _ in ROOT_OPTIONS)
    short_width = max(len(short) for _, short, _ in ROOT_OPTIONS)
    option_rows = []
    for name, short, help_text in ROOT_OPTIONS:
        plain = f" {name.ljust(name_width)}  {short.ljust(short_width)}" + " " * 8
        cell = (" " + sgr("-", "1", "36") + sgr(name[1:], "1", "36") + " " * (name_width - len(name)) + "  "
                + (sgr(short, "1", "32") if short else "") + " " * (short_width - len(short)) + " " * 8
                if styled else plain)
        option_rows.append(([cell, " " * len(plain)], help_text))
    panel("Options", option_rows, len(option_rows[0][0][1]) + 1)

    command_width = max(len(command.name) for command in listed())
    command_rows = []
    for command in listed():
        cell = " " + sgr(command.name.ljust(command_width), "1", "36") + sgr(" ", "1", "36") + " "
        blank = " " + sgr(" " * (command_width + 1), "1", "36") + " "
        command_rows.append(([cell, blank], command.summary))
    panel("Commands", command_rows, command_width + 4)
    return "\n".join(lines) + "\n\n"
