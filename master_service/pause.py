"""A run that waits for a person: batteries to swap, robots to place (docs/runs.md).

The run pauses only between evaluations, after its checkpoint is on disk, every robot idle with
its motors stopped (an agent stops them at the end of every evaluation). While it waits,
``pause.json`` in the run directory says why, which robots, and since when; ``status``, the
dashboard and the live telemetry show it. ``surprise-master continue RUN_DIR`` removes the file
(:func:`request_continue`), and so does Enter on the master's console; the run goes on from where
it stood, nothing restarted. A master stopped while paused (SIGTERM) resumes with
``surprise-master resume RUN_DIR`` as any stopped run, the stale file removed.

A pause for low batteries names the robots whose battery read below ``battery_min_v`` after the
last evaluation; the next evaluation's readings are checked again, so a robot continued without a
fresh battery pauses the run again.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final

from master_service.console import Console, terminal_usable
from master_service.rundir import RunDir, RunDirError
from minimize_surprise.wire import EvaluationStats
from runfiles import schema
from runfiles.schema import PauseFile, PauseNote

__all__ = [
    "PAUSE",
    "POLL_INTERVAL",
    "Pause",
    "PauseGate",
    "low_batteries",
    "read_pause",
    "request_continue",
]

#: Seconds between two looks for ``pause.json``'s removal: far below a person's reaction, and
#: one ``stat`` call each.
POLL_INTERVAL: Final = 0.25

#: The file that says the run waits.
PAUSE: Final = PauseFile.FILE


@dataclass(frozen=True)
class Pause:
    """Why a run waits: ``kind`` (``battery``, ``robot-gone`` or ``before-post-evaluation``),
    one line for a person (``text``), and the robots concerned (none: the whole swarm)."""

    kind: str
    text: str
    robots: tuple[str, ...] = ()

    def note(self) -> PauseNote:
        """The pause as ``live.json`` tells it: ``kind``, ``reason`` and ``robots``."""
        return PauseNote(kind=self.kind, reason=self.text, robots=list(self.robots))

    def to_file(self, since: float) -> PauseFile:
        """``pause.json``: :meth:`note` and when the pause began."""
        return PauseFile(kind=self.kind, reason=self.text, robots=list(self.robots), since=since)


def low_batteries(
    robots: Sequence[str], stats: Sequence[EvaluationStats], threshold: float | None
) -> Pause | None:
    """A battery pause for the robots whose battery read below ``threshold`` volts, or None.

    A robot that reports no battery (Aseba Playground, simulation) never pauses a run.
    """
    if threshold is None or not stats:
        return None
    low = [
        (robot, s.battery_v)
        for robot, s in zip(robots, stats, strict=True)
        if s.battery_v is not None and s.battery_v < threshold
    ]
    if not low:
        return None
    named = ", ".join(f"{robot} ({volts:.2f} V)" for robot, volts in low)
    text = f"battery below {threshold:.2f} V: swap the battery of {named}"
    return Pause("battery", text, tuple(robot for robot, _ in low))


def read_pause(run_dir: RunDir) -> PauseFile | None:
    """``pause.json`` while the run waits, else None (also for a file this version cannot read:
    the pause is then the master's to tell, and ``continue`` still removes the file)."""
    return schema.read_if_readable(run_dir.path, PauseFile)


def request_continue(run_dir: RunDir) -> PauseFile | None:
    """Let a paused run go on (``surprise-master continue``); the pause it ends (None when its
    file could not be read).

    Raises :class:`RunDirError` when the run does not wait.
    """
    pause = read_pause(run_dir)
    path = run_dir.file(PAUSE)
    try:
        path.unlink()
    except FileNotFoundError:
        raise RunDirError(f"{run_dir.path} is not paused (no {PAUSE})") from None
    return pause


class PauseGate:
    """Holds a run while it is paused; the one place that writes and waits for ``pause.json``.

    ``console``: Enter on the master's terminal continues too (only when stdin is a terminal in
    the foreground); ``terminal`` the master's :class:`~master_service.console.Console` that
    reads it for the whole run (None: the gate reads the terminal itself while it waits).
    """

    def __init__(
        self,
        run_dir: RunDir,
        log: logging.Logger,
        *,
        console: bool = False,
        terminal: Console | None = None,
    ) -> None:
        self.run_dir = run_dir
        self.log = log
        self.console = console
        self.terminal = terminal
        #: the pause the run waits in now, None while it runs
        self.current: Pause | None = None

    def clear_stale(self) -> None:
        """Remove a ``pause.json`` left by a master that stopped while paused: resuming is the
        person's go-ahead."""
        with contextlib.suppress(FileNotFoundError):
            self.run_dir.file(PAUSE).unlink()

    async def wait(
        self, pause: Pause, on_change: Any = None, over: Callable[[], bool] | None = None
    ) -> float:
        """Announce ``pause`` and wait until a person lets the run go on; the seconds waited.

        ``on_change()`` (optional) is called when the pause starts and when it ends. ``over()``
        (optional), asked at every look, ends the pause when what it waits for was settled
        otherwise (a robot gone for good swapped for a spare, or back).
        """
        since = time.time()
        await asyncio.to_thread(schema.write, self.run_dir.path, pause.to_file(since))
        self.current = pause
        how = f"surprise-master continue {self.run_dir.path}"
        if self._console_usable():
            how += " (or Enter here)"
        self.log.warning("paused: %s; then: %s", pause.text, how)
        if on_change is not None:
            on_change()
        terminal = self.terminal or Console(self.log)
        started = time.monotonic()
        with contextlib.ExitStack() as stack:
            if self.console and not terminal.active:
                stack.enter_context(terminal.reading())
            terminal.arm()
            entered = terminal.enter()
            try:
                while (
                    self.run_dir.file(PAUSE).exists()
                    and not (self.console and entered.is_set())
                    and not (over is not None and over())
                ):
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(POLL_INTERVAL):
                            await entered.wait()
            finally:
                self.current = None
        self.clear_stale()
        waited = time.monotonic() - started
        self.log.info("continued after a pause of %.0f s (%s)", waited, pause.kind)
        if on_change is not None:
            on_change()
        return waited

    def _console_usable(self) -> bool:
        return self.console and terminal_usable()
