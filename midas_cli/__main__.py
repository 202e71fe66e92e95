"""The process entry point (`midas` and `python -m midas_cli`).

Ctrl-C is quiet from the first instant: until a command installs its own handling (`midas record`
turns it into a stop request), SIGINT ends the process with one line and exit 130, never a
KeyboardInterrupt traceback from the middle of an import.
"""

import signal
import sys


def _interrupted(_signum, _frame) -> None:
    sys.stderr.write("midas: interrupted\n")
    raise SystemExit(130)


def main() -> None:
    signal.signal(signal.SIGINT, _interrupted)
    from midas_cli.commands.root import answer_without_typer

    status = answer_without_typer(sys.argv[1:])  # --version and the root help need no command module
    if status is not None:
        sys.exit(status)
    from midas_cli.commands.main import run

    run()


if __name__ == "__main__":
    main()
