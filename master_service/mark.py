"""A person marks a change they made to a running run: ``surprise-master mark RUN_DIR "moved the
light"``, or ``mark moved the light`` typed in the master's console (docs/changing-arenas.md).

The command drops a :class:`~runfiles.schema.MarkRequest` through the request desk
(:mod:`master_service.desk`); the master's mark desk takes it between or during evaluations and
appends a ``mark`` event naming the counted evaluations done then and the run's served seconds.
The report reads marks as it reads the experiment's events: fitness around each.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Final

from master_service import desk
from master_service.console import Console
from master_service.escape import escape_from_console
from master_service.rundir import RunDir, RunState
from runfiles.schema import EVENT_MARK, Event, MarkRequest, RunDirError

__all__ = ["MARK_TIMEOUT", "MarkDesk", "hand_console", "mark_from_console", "request_mark"]

#: Seconds ``surprise-master mark`` waits for the master's answer.
MARK_TIMEOUT: Final = 10.0
#: Seconds between two looks of the desk for a mark.
POLL_INTERVAL: Final = 0.2
#: The longest mark's text: a line, not a file.
MAX_TEXT: Final = 500


def _request(text: str) -> MarkRequest:
    text = " ".join(text.split())
    if not text:
        raise RunDirError("a mark needs a text: what changed")
    if len(text) > MAX_TEXT:
        raise RunDirError(f"a mark's text is one line of at most {MAX_TEXT} characters")
    return MarkRequest(text=text, token=desk.new_token(), requested_at=time.time())


def request_mark(run_dir: RunDir, text: str, *, timeout: float = MARK_TIMEOUT) -> Event:
    """Mark ``text`` on the run the master serves in ``run_dir``; the ``mark`` event it wrote.

    Raises :class:`RunDirError` when no master runs the run, for an empty text, or when the
    master does not answer within ``timeout``.
    """
    return desk.ask_master(
        run_dir.path,
        _request(text),
        EVENT_MARK,
        timeout=timeout,
        not_running=f"no master is running {run_dir.path}: a mark needs a running run",
    )


def mark_from_console(run_dir: RunDir, log: logging.Logger) -> Callable[[str], None]:
    """What a ``mark TEXT`` line on the master's terminal does: the request ``surprise-master
    mark`` drops; the desk logs the mark."""

    def mark(text: str) -> None:
        try:
            desk.drop_request(run_dir.path, _request(text))
        except (RunDirError, OSError) as exc:
            log.warning("the mark %r: %s", text, exc)

    return mark


def hand_console(run_dir: RunDir, log: logging.Logger) -> Console:
    """The master's console for the run in ``run_dir``: its ``escape ROBOT`` and ``mark TEXT``
    lines drop the requests the commands drop."""
    return Console(
        log, escape=escape_from_console(run_dir, log), mark=mark_from_console(run_dir, log)
    )


class MarkDesk:
    """The master's desk for marks: each becomes a ``mark`` event with the counted evaluations
    of ``state()`` and the run's served seconds ``elapsed()``."""

    def __init__(
        self,
        run_dir: RunDir,
        log: logging.Logger,
        state: Callable[[], RunState | None],
        elapsed: Callable[[], float],
    ) -> None:
        self.run_dir = run_dir
        self.log = log
        self._state = state
        self._elapsed = elapsed

    async def run(self) -> None:
        """Answer marks until cancelled, in the order they came."""
        await desk.serve_requests(
            self.run_dir.path, MarkRequest, self.handle, self.log, "the mark",
            lambda: POLL_INTERVAL,
        )  # fmt: skip

    async def handle(self, request: MarkRequest) -> Event:
        """The ``mark`` event of ``request``, at the evaluations counted now."""
        state = self._state()
        evaluations = 0 if state is None else state.optimizer.evaluations
        self.log.info("marked after evaluation %d: %s", evaluations, request.text)
        return Event(
            time=time.time(),
            kind=EVENT_MARK,
            request=request.token,
            accepted=True,
            evaluation=evaluations,
            seconds=round(self._elapsed(), 3),
            detail=request.text,
        )
