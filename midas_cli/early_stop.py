"""The stop signal the entry point (``__main__``) answered before a command installed its own handling.

``__main__`` ends the process on SIGINT/SIGTERM/SIGHUP by raising ``SystemExit`` from its handler, but
the handler runs wherever the interpreter happens to be, and an exception raised there can be lost
(once in CI: `midas record` printed "midas: stopped by SIGTERM" and then recorded its whole
``--duration``). The handler notes the signal here first; a command that installs its own handling
(`midas record`) checks the note right after and ends as the signal asked: exit 128 + the signal
number, nothing created, the one line already said."""

from typing import Optional

received: Optional[int] = None
