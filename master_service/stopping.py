"""Stopping a command cleanly on SIGINT or SIGTERM: the run commits and says where it stands.

Two ways, for two kinds of work: :func:`stop_flag` notes the signal for a run that asks between
evaluations (the compiled engine, whose evaluations are single compiled calls that a signal must
not interrupt mid-write); :func:`until_signal` cancels an asyncio task, whose own clean-up stops
the robots and closes the run.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
from collections.abc import Awaitable, Iterator
from typing import Any, Final, TypeVar

__all__ = ["STOP_SIGNALS", "cancelled_by_signal", "stop_flag", "until_signal"]

T = TypeVar("T")

#: The signals that stop a run cleanly (it can be resumed).
STOP_SIGNALS: Final = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def stop_flag(received: list[int]) -> Iterator[None]:
    """While inside, SIGINT and SIGTERM are noted in ``received`` (the run asks between
    evaluations) instead of raising KeyboardInterrupt in the middle of a write."""

    def note(signum: int, frame: object) -> None:
        received.append(signum)

    previous = {signum: signal.signal(signum, note) for signum in STOP_SIGNALS}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


@contextlib.contextmanager
def cancelled_by_signal(task: asyncio.Task[Any], received: list[int]) -> Iterator[None]:
    """While inside (in the event loop), the first SIGINT or SIGTERM is noted in ``received`` and
    cancels ``task``; later ones are ignored, so the clean-up the first started is not cut short."""
    loop = asyncio.get_running_loop()

    def stop(signum: int) -> None:
        if not received:
            received.append(signum)
            task.cancel()

    for signum in STOP_SIGNALS:
        loop.add_signal_handler(signum, stop, signum)
    try:
        yield
    finally:
        for signum in STOP_SIGNALS:
            loop.remove_signal_handler(signum)


async def until_signal(work: Awaitable[T], received: list[int]) -> T | None:
    """Await ``work``; on SIGINT or SIGTERM cancel it (its own clean-up runs) and return None."""
    task = asyncio.ensure_future(work)
    with cancelled_by_signal(task, received):
        try:
            return await task
        except asyncio.CancelledError:
            if not received:
                raise
            return None
