"""The process entry point (`midas` and `python -m midas_cli`).

A stop signal is quiet from the first instant midas code runs: until a command installs its own
handling (`midas record` turns them into a stop request), SIGINT, SIGTERM and SIGHUP end the process
with one line and exit 128 + the signal number, never a KeyboardInterrupt traceback from the middle
of an import. (What arrives before this module runs, while the Python interpreter itself starts, is
the interpreter's to handle.)
"""

import signal
import sys

from midas_cli import early_stop

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def _stopped(signum: int, _frame) -> None:
    early_stop.received = signum  # first: read by a command that installs its own handling (early_stop)
    try:
        sys.stderr.write(f"midas: stopped by {signal.Signals(signum).name}\n")
    except (OSError, ValueError):  # the terminal is gone (a hang-up) or stderr is closed
        pass
    raise SystemExit(128 + signum)


def main() -> None:
    for signum in STOP_SIGNALS:
        signal.signal(signum, _stopped)
    from midas_cli.commands.root import answer_without_typer

    status = answer_without_typer(sys.argv[1:])  # --version and the root help need no command module
    if status is not None:
        sys.exit(status)
    from midas_cli.commands.main import run

    run()


if __name__ == "__main__":
    main()
