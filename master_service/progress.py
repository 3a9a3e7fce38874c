"""The command line's view of a running master: a live panel on a terminal, plain lines otherwise.

On a terminal (TTY) a rich live panel shows evaluations done, best fitness, robots connected and
time left, with the log scrolling above it. Anywhere else (a pipe, a file, systemd's journal) there
is no panel: the master's own log lines carry the same figures, one line per counted evaluation.
"""

from __future__ import annotations

import logging
import sys
from typing import IO, Any

from master_service.evaluation import Progress
from master_service.rundir import for_console
from minimize_surprise.safety import SAFETY_DOMINATES
from minimize_surprise.text import format_duration, plural
from telemetry.payloads import RunStatus, now

__all__ = ["ProgressDisplay", "describe", "planned_text"]

#: Redraws per second of the live panel: smooth enough for a clock, cheap for the event loop.
REFRESH_PER_SECOND = 4
_FORMAT = "%(asctime)s %(levelname)s %(message)s"


def planned_text(evaluations: int | None) -> str:
    """The evaluations a run plans, as its first line says them: ``300 evaluations``, or
    ``endless evaluations`` (``evaluations: null``)."""
    return "endless evaluations" if evaluations is None else plural(evaluations, "evaluation")


def describe(progress: Progress) -> str:
    """One line with the figures of ``progress``."""
    best = "-" if progress.best_fitness is None else f"{progress.best_fitness:.4f}"
    if progress.phase == "done":
        state = "done"
    elif progress.waiting:
        state = "waiting for robots"
    else:
        state = progress.phase
    left = "-" if progress.time_left_s is None else format_duration(progress.time_left_s)
    safety = "-" if progress.safety_share is None else f"{100 * progress.safety_share:.0f} %"
    return (
        f"{state} | evaluations {progress.evaluations}/{progress.total or 'endless'} | "
        f"best {best} | "
        f"robots {progress.robots_connected}/{progress.robots_expected} | "
        f"safety drove {safety} | failed attempts {progress.failed_attempts} | elapsed "
        f"{format_duration(progress.elapsed_s)} | left ~{left}"
    )


class ProgressDisplay:
    """Console logging for the ``master_service`` loggers, plus the live panel on a TTY.

    Use as a context manager around the run; pass :meth:`update` to
    :meth:`~master_service.master.Master.add_progress_listener`. ``live`` forces the panel on or
    off (default: on when ``stream`` is a terminal).
    """

    def __init__(
        self,
        stream: IO[str] | None = None,
        *,
        live: bool | None = None,
        level: int = logging.INFO,
    ) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.live = self.stream.isatty() if live is None else live
        self.level = level
        self._logger = logging.getLogger("master_service")
        self._handler: logging.Handler | None = None
        self._live: Any = None
        self._last: Progress | None = None

    def __enter__(self) -> ProgressDisplay:
        if self.live:
            # rich only when there is a terminal to draw on: imported here, not at module load.
            from rich.console import Console
            from rich.live import Live
            from rich.logging import RichHandler

            console = Console(file=self.stream)
            self._handler = RichHandler(console=console, show_path=False)
            self._live = Live(
                self._render(), console=console, refresh_per_second=REFRESH_PER_SECOND
            )
            self._live.start()
        else:
            self._handler = logging.StreamHandler(self.stream)
            self._handler.setFormatter(logging.Formatter(_FORMAT))
        # The console's level is the handler's: the run's log file below keeps every INFO line
        # whatever the console shows.
        self._handler.setLevel(self.level)
        self._handler.addFilter(for_console)
        self._logger.addHandler(self._handler)
        self._logger.setLevel(min(self.level, logging.INFO))
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self._live is not None:
            self._live.stop()
            self._live = None
        if self._handler is not None:
            self._logger.removeHandler(self._handler)
            self._handler = None

    def update(self, progress: Progress) -> None:
        """Show ``progress`` (the panel redraws at its own pace; without a panel: nothing)."""
        self._last = progress
        if self._live is not None:
            self._live.update(self._render())

    def _render(self) -> Any:
        from rich.panel import Panel
        from rich.progress_bar import ProgressBar
        from rich.table import Table

        progress = self._last
        if progress is None:
            return Panel("starting...", title="surprise-master")
        grid = Table.grid(padding=(0, 2))
        grid.add_column(style="bold")
        grid.add_column()
        grid.add_column()
        bar = ProgressBar(total=progress.total, completed=progress.evaluations, width=30)
        done = f"{progress.evaluations}/{progress.total or 'endless'}"
        grid.add_row("evaluations", done, bar)
        best = "-" if progress.best_fitness is None else f"{progress.best_fitness:.4f}"
        last = "-" if progress.last_fitness is None else f"{progress.last_fitness:.4f}"
        grid.add_row("best fitness", best, f"last {last}")
        if progress.safety_share is not None:
            share = progress.safety_share
            warning = (
                "  the safety layer does most of the driving" if share > SAFETY_DOMINATES else ""
            )
            grid.add_row(
                "safety drove",
                f"{100 * share:.0f} % of steps",
                warning,
                style="" if not warning else "yellow",
            )
        robots = f"{progress.robots_connected}/{progress.robots_expected}"
        grid.add_row("robots", robots, "waiting for robots" if progress.waiting else "")
        left = "-" if progress.time_left_s is None else format_duration(progress.time_left_s)
        grid.add_row("time left", f"~{left}", f"elapsed {format_duration(progress.elapsed_s)}")
        grid.add_row("phase", progress.phase, f"failed attempts {progress.failed_attempts}")
        return Panel(grid, title=f"surprise-master: run {progress.run_id}", expand=False)


def run_status(progress: Progress, robots: list[str], *, online: bool = True) -> RunStatus:
    """The retained ``<prefix>/run/status`` telemetry of ``progress`` with ``robots`` connected."""
    return RunStatus(
        t=now(),
        online=online,
        run_id=progress.run_id,
        phase=progress.phase,
        waiting=progress.waiting,
        evaluations=progress.evaluations,
        total=progress.total or 0,  # 0: an endless run
        best_fitness=progress.best_fitness,
        last_fitness=progress.last_fitness,
        robots_connected=progress.robots_connected,
        robots_expected=progress.robots_expected,
        robots=robots,
        failed_attempts=progress.failed_attempts,
        elapsed_s=round(progress.elapsed_s, 3),
        time_left_s=None if progress.time_left_s is None else round(progress.time_left_s, 1),
        paused=progress.paused,
    )
