"""A log that writes at most a bounded number of lines per window and counts the rest.

For events that anyone on the network can cause as often as they like (connections refused or
failing before authentication): each may be worth a line, ten thousand of them are not, and a
flood of them must not fill the disk or bury the lines that matter. The lines held back are
counted and reported in one line when the next window opens (or at :meth:`ThrottledLog.flush`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any, Final

__all__ = ["DEFAULT_LINES_PER_WINDOW", "DEFAULT_WINDOW", "ThrottledLog"]

#: Lines let through per window by default: enough to see what is going on, few enough that a
#: flood costs a handful of lines a minute.
DEFAULT_LINES_PER_WINDOW: Final = 10
#: Seconds of one window by default.
DEFAULT_WINDOW: Final = 60.0


class ThrottledLog:
    """Writes to ``logger`` at most ``lines`` lines per ``window`` seconds, plus one line per
    window that says how many were held back (``what`` names them in that line).

    ``clock`` returns seconds (monotonic); tests pass their own.
    """

    def __init__(
        self,
        logger: logging.Logger | logging.LoggerAdapter,
        what: str,
        *,
        lines: int = DEFAULT_LINES_PER_WINDOW,
        window: float = DEFAULT_WINDOW,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if lines < 1 or window <= 0:
            raise ValueError("lines must be at least 1 and window positive")
        self.logger = logger
        self.what = what
        self.lines = lines
        self.window = window
        self._clock = clock
        self._window_start: float | None = None
        self._written = 0
        #: lines held back in the current window
        self.suppressed = 0
        #: lines held back since the start
        self.suppressed_total = 0

    def log(self, level: int, msg: str, *args: Any) -> bool:
        """Write the line if this window has room; returns whether it was written."""
        now = self._clock()
        if self._window_start is None or now - self._window_start >= self.window:
            self.flush()
            self._window_start = now
            self._written = 0
        if self._written >= self.lines:
            self.suppressed += 1
            self.suppressed_total += 1
            return False
        self._written += 1
        self.logger.log(level, msg, *args)
        return True

    def flush(self) -> None:
        """Write the count of the lines held back in the current window, if any."""
        if self.suppressed:
            self.logger.warning(
                "%d more %s were not logged (at most %d lines per %g s)",
                self.suppressed,
                self.what,
                self.lines,
                self.window,
            )
            self.suppressed = 0
