"""Keys on the live recording screen: ``m``, a line of text, Enter adds a marker; Esc cancels.

Read only while the live screen is on and stdin is the terminal in the foreground (a recorder started
with ``&`` never touches the terminal's modes). The terminal goes to cbreak without echo (Ctrl-C still
stops the recording) and is put back as it was on every exit path. SIGTTIN and SIGTTOU are ignored
meanwhile: a recorder sent to the background (Ctrl-Z, ``bg``) keeps recording instead of being stopped
by the terminal; it reads no keys until it is in the foreground again.
"""

from __future__ import annotations

import codecs
import logging
import os
import select
import signal
import sys
import termios
import threading
from typing import Callable, Optional

log = logging.getLogger(__name__)

ESC, ENTER, BACKSPACE, KILL_LINE = 0x1B, (0x0D, 0x0A), (0x7F, 0x08), 0x15
MAX_PROMPT = 200  # characters typed into one marker


class MarkerPrompt:
    """The marker being typed, fed the terminal's bytes. ``text`` is None while no marker is typed."""

    def __init__(self) -> None:
        self.text: Optional[str] = None
        self._decoder = codecs.getincrementaldecoder("utf-8")("replace")

    def feed(self, data: bytes) -> list[str]:
        """Take a read's bytes; return the markers finished (Enter) in them."""
        done: list[str] = []
        i = 0
        while i < len(data):
            byte = data[i]
            if byte == ESC:
                if i + 1 == len(data):  # a lone Esc: cancel
                    self.text = None
                i = _skip_escape_sequence(data, i)
                continue
            i += 1
            if self.text is None:
                if byte in (ord("m"), ord("M")):
                    self.text = ""
                continue
            if byte in ENTER:
                if self.text.strip():
                    done.append(self.text)
                self.text = None
            elif byte in BACKSPACE:
                self.text = self.text[:-1]
            elif byte == KILL_LINE:
                self.text = ""
            elif byte >= 0x20:
                typed = self._decoder.decode(bytes([byte]))
                self.text = (self.text + typed)[:MAX_PROMPT]
        return done


def _skip_escape_sequence(data: bytes, i: int) -> int:
    """The index after the escape sequence starting at ``data[i]`` (an arrow key, F-key...)."""
    j = i + 1
    if j < len(data) and data[j] in (ord("["), ord("O")):
        j += 1
        while j < len(data) and not 0x40 <= data[j] <= 0x7E:
            j += 1
        return j + 1
    return j


def keyboard_available() -> bool:
    """True when stdin is a terminal and this process is in its foreground (may read it and set modes)."""
    try:
        fd = sys.stdin.fileno()
        return os.isatty(fd) and os.tcgetpgrp(fd) == os.getpgrp()
    except (OSError, ValueError, AttributeError):
        return False


class Keyboard:
    """Feeds the terminal's keys to a ``MarkerPrompt`` in a thread; ``on_marker(text)`` per finished one."""

    def __init__(self, prompt: MarkerPrompt, on_marker: Callable[[str], None]) -> None:
        self.prompt = prompt
        self.on_marker = on_marker
        self._fd = sys.stdin.fileno()
        self._saved: Optional[list] = None
        self._signals: dict = {}
        self._stopping = threading.Event()
        self._thread: Optional[threading.Thread] = None

    def __enter__(self) -> "Keyboard":
        for sig in (signal.SIGTTIN, signal.SIGTTOU):
            self._signals[sig] = signal.signal(sig, signal.SIG_IGN)
        self._saved = termios.tcgetattr(self._fd)
        mode = termios.tcgetattr(self._fd)
        mode[3] &= ~(termios.ECHO | termios.ICANON)  # lflag: keys one at a time, not shown; ISIG stays
        mode[6][termios.VMIN], mode[6][termios.VTIME] = 1, 0
        termios.tcsetattr(self._fd, termios.TCSADRAIN, mode)
        self._thread = threading.Thread(target=self._loop, name="midas-keys", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        if self._saved is not None:
            try:
                termios.tcsetattr(self._fd, termios.TCSADRAIN, self._saved)
            except (termios.error, OSError):  # the terminal is gone (hang-up): nothing to restore
                pass
        for sig, handler in self._signals.items():
            signal.signal(sig, handler)

    def _loop(self) -> None:
        while not self._stopping.is_set():
            try:
                ready, _, _ = select.select([self._fd], [], [], 0.1)
                data = os.read(self._fd, 256) if ready else None
            except OSError:  # in the background (EIO), or the terminal hung up: try again later
                self._stopping.wait(0.2)
                continue
            if data == b"":
                return
            for text in self.prompt.feed(data or b""):
                self.on_marker(text)
