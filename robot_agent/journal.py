"""The agent's output: log lines on stdout and error messages on stderr, with priorities for
journald, log lines with a time stamp elsewhere.

Under systemd, stdout is a stream to the journal, which takes each line as one entry of priority
"info" and stamps it with its own time. A line that starts with a syslog priority (``<3>`` error,
``<4>`` warning, ...) gets that priority instead, so ``journalctl -p warning -u surprise-agent``
shows what went wrong. systemd names that stream in ``JOURNAL_STREAM`` (``DEV:INODE``); the
prefix is written only to that very stream, not to a terminal or file it may have been swapped
for (``surprise-agent > log``, a shell started from the unit).
"""

from __future__ import annotations

import logging
import os
import sys
from typing import TextIO

__all__ = [
    "JOURNAL_FORMAT",
    "PLAIN_FORMAT",
    "JournalFormatter",
    "is_journal",
    "print_error",
    "priority",
    "setup_logging",
]

#: A line outside journald: its own time stamp.
PLAIN_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
#: A line for journald, which stamps the time itself (the priority prefix comes in front).
JOURNAL_FORMAT = "%(levelname)s %(name)s: %(message)s"

# syslog priorities (sd-daemon(3)) from the highest logging level down; anything lower is debug.
_PRIORITIES = (
    (logging.CRITICAL, 2),
    (logging.ERROR, 3),
    (logging.WARNING, 4),
    (logging.INFO, 6),
)
_DEBUG = 7


def priority(levelno: int) -> int:
    """The syslog priority of a logging level (``<N>`` in front of a journal line)."""
    for level, value in _PRIORITIES:
        if levelno >= level:
            return value
    return _DEBUG


def _prefixed(text: str, levelno: int) -> str:
    # journald splits a stream at newlines only, and reads a prefix at the start of each line.
    prefix = f"<{priority(levelno)}>"
    return "\n".join(prefix + line for line in text.split("\n"))


class JournalFormatter(logging.Formatter):
    """Formats a record for journald: every line starts with the record's priority ``<N>``.

    journald makes each line of a stream a separate entry, so a traceback's lines all carry the
    prefix too, or they would be logged as "info" under the error they belong to.
    """

    def __init__(self) -> None:
        super().__init__(JOURNAL_FORMAT)

    def format(self, record: logging.LogRecord) -> str:
        """The record's text, each line prefixed with its priority."""
        return _prefixed(super().format(record), record.levelno)


def is_journal(stream: TextIO) -> bool:
    """Whether ``stream`` is the journal stream systemd passed (``JOURNAL_STREAM=DEV:INODE``)."""
    device, colon, inode = os.environ.get("JOURNAL_STREAM", "").partition(":")
    if not colon:
        return False
    try:
        status = os.fstat(stream.fileno())
        return (status.st_dev, status.st_ino) == (int(device), int(inode))
    except (AttributeError, OSError, ValueError):  # no file behind it (pytest), a bad variable
        return False


def print_error(message: str) -> None:
    """Print ``message`` on stderr, as an error (``<3>``) when stderr is the journal stream.

    For what the agent says before logging is set up or instead of a log line (a bad
    configuration, a motor stop that was not confirmed): as "info" it would drown in the journal.
    """
    print(_prefixed(message, logging.ERROR) if is_journal(sys.stderr) else message, file=sys.stderr)


def setup_logging(level: str, stream: TextIO | None = None) -> None:
    """Log at ``level`` to ``stream`` (default stdout), in the journal's form when it is one.

    Leaves an already configured root logger alone (an embedding process, pytest).
    """
    stream = sys.stdout if stream is None else stream
    handler = logging.StreamHandler(stream)
    handler.setFormatter(
        JournalFormatter() if is_journal(stream) else logging.Formatter(PLAIN_FORMAT)
    )
    logging.basicConfig(level=level, handlers=[handler])
