"""The master's terminal while it serves a run: a person's hand without a second shell.

Two things can be typed where ``surprise-master run`` (or ``resume``) shows its progress:

* Enter: a paused run goes on, as ``surprise-master continue RUN_DIR`` does (docs/runs.md);
* ``escape ROBOT`` (or ``e ROBOT``) and Enter: that robot runs its safety layer's escape now, as
  ``surprise-master escape RUN_DIR ROBOT`` does (paper Sec. V-C, docs/safety.md). The line drops
  the same request into the run directory; the master's escape desk takes it and logs how it
  went.
* ``mark TEXT`` and Enter: the change a person just made (``mark moved the light``) goes into
  the run's events with the evaluation it happened at, as ``surprise-master mark RUN_DIR TEXT``
  does (docs/changing-arenas.md).

The terminal is read only when stdin is one and the master runs in its foreground: reading it
from the background (``&``) would stop the whole master (SIGTTIN). Anything else typed gets one
line saying what the console knows.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import sys
import termios
from collections.abc import Callable, Iterator

__all__ = ["Console", "terminal_usable"]

#: The words that ask for an escape, followed by the robot's id.
ESCAPE_WORDS = ("escape", "e")


def terminal_usable() -> bool:
    """Whether stdin is a terminal this process may read: it is one, and the process runs in
    its foreground."""
    if sys.stdin is None or not sys.stdin.isatty():
        return False
    try:
        return os.tcgetpgrp(sys.stdin.fileno()) == os.getpgrp()
    except OSError:
        return False


class Console:
    """Reads the master's terminal on the running event loop (see the module docstring).

    ``escape(robot)`` is called for an ``escape ROBOT`` line (None: the console has no run to
    escape in, and says so). Use :meth:`reading` around the serving; :meth:`enter` is the event
    a pause waits on, :meth:`arm` clears it (and what was typed before) when a pause begins.
    """

    def __init__(
        self,
        log: logging.Logger,
        *,
        escape: Callable[[str], None] | None = None,
        mark: Callable[[str], None] | None = None,
    ):
        self.log = log
        self.escape = escape
        #: called with the text of a ``mark TEXT`` line (None: the console has no run)
        self.mark = mark
        self._entered: asyncio.Event | None = None
        self._fd: int | None = None
        self._pending = b""

    @property
    def active(self) -> bool:
        """Whether the terminal is being read now."""
        return self._fd is not None

    def enter(self) -> asyncio.Event:
        """Set when Enter was pressed on an empty line (since :meth:`arm`)."""
        if self._entered is None:
            self._entered = asyncio.Event()
        return self._entered

    def arm(self) -> None:
        """Forget an Enter pressed before now, and the half-typed line: only a key pressed from
        now on counts (a line typed before a pause began must not end it)."""
        self.enter().clear()
        self._pending = b""
        if self._fd is not None:
            with contextlib.suppress(OSError, termios.error):
                termios.tcflush(self._fd, termios.TCIFLUSH)

    @contextlib.contextmanager
    def reading(self) -> Iterator[Console]:
        """Read the terminal while the block runs, if it may be read (:func:`terminal_usable`)."""
        opened = self._open()
        try:
            yield self
        finally:
            if opened:
                self._close()

    def _open(self) -> bool:
        if self._fd is not None or not terminal_usable():
            return False
        fd = sys.stdin.fileno()
        try:
            asyncio.get_running_loop().add_reader(fd, self._on_input)
        except (NotImplementedError, OSError, ValueError, RuntimeError):
            return False
        self._fd = fd
        return True

    def _close(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError, ValueError, RuntimeError):
                asyncio.get_running_loop().remove_reader(self._fd)
            self._fd = None

    def _on_input(self) -> None:
        assert self._fd is not None
        try:
            data = os.read(self._fd, 1024)
        except OSError:
            return
        if not data:  # the terminal went away: stop reading it
            self._close()
            return
        self._pending += data
        *lines, self._pending = self._pending.split(b"\n")
        for line in lines:
            self.line(line.decode(errors="replace"))

    def line(self, text: str) -> None:
        """Act on one line typed (without its newline)."""
        words = text.split()
        if not words:
            self.enter().set()
        elif len(words) >= 2 and words[0].lower() == "mark":
            if self.mark is None:
                self.log.warning("no run to mark")
            else:
                self.mark(" ".join(words[1:]))
        elif len(words) == 2 and words[0].lower() in ESCAPE_WORDS:
            if self.escape is None:
                self.log.warning("no run to escape in")
            else:
                self.escape(words[1])
        else:
            self.log.warning(
                "the console knows: Enter (a paused run goes on), 'escape ROBOT' (that "
                "robot escapes now) and 'mark TEXT' (a change you made); not %r",
                text.strip(),
            )
