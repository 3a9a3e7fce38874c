"""The progress of a study on the terminal: a bar with runs done, running, failed and time left
on a TTY; a plain line per finished run otherwise."""

from __future__ import annotations

import sys
from types import TracebackType
from typing import TYPE_CHECKING, Self

from studies.runner import Counts

if TYPE_CHECKING:
    from rich.progress import Progress, TaskID

__all__ = ["StudyProgress"]


def _duration(seconds: float) -> str:
    seconds = int(seconds)
    if seconds >= 3600:
        return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"
    if seconds >= 60:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds} s"


def _time_left(counts: Counts, elapsed: float) -> str:
    finished = counts.done - counts.skipped + counts.failed
    if finished <= 0 or counts.left <= 0:
        return "-"
    return _duration(elapsed / finished * counts.left)


class StudyProgress:
    """Use as a context manager; pass :meth:`update` as the runner's ``on_update``."""

    def __init__(self) -> None:
        self.live = sys.stdout.isatty()
        self._progress: Progress | None = None
        self._task: TaskID | None = None

    def __enter__(self) -> Self:
        if self.live:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

            self._progress = Progress(
                TextColumn("runs"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[detail]}"),
            )
            self._progress.start()
            self._task = self._progress.add_task("study", total=None, detail="starting")
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._progress is not None:
            self._progress.stop()

    def update(self, counts: Counts, elapsed: float) -> None:
        """Show where the study stands."""
        detail = (
            f"running {counts.running}, failed {counts.failed}, left ~{_time_left(counts, elapsed)}"
        )
        if self._progress is not None:
            assert self._task is not None  # added with the progress in __enter__
            self._progress.update(
                self._task, total=counts.total, completed=counts.done, detail=detail
            )
        elif elapsed > 0:
            print(f"runs {counts.done}/{counts.total}, {detail}", flush=True)
