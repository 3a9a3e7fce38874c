"""Clean-up that must happen, bounded in time: :func:`finish`.

Kept apart from the runner so that ``surprise-agent --stop-motors`` can use it without importing
the agent's numerical side (numpy, the networks, the safety layer).
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable

__all__ = ["finish"]


async def finish(awaitable: Awaitable[object], timeout: float) -> BaseException | None:
    """Await ``awaitable`` for at most ``timeout`` seconds, even if the caller is cancelled.

    For clean-up that must happen (stopping the motors) on paths where the calling task may be
    cancelled again. Returns None on success, else the exception (``TimeoutError`` if it did not
    finish in time; it is then cancelled). If the caller was cancelled meanwhile, the
    cancellation is re-raised after the clean-up finished.
    """
    loop = asyncio.get_running_loop()
    try:
        task = asyncio.ensure_future(awaitable)
    except Exception as exc:  # not awaitable, or a coroutine function that raised at once
        return exc
    end = loop.time() + timeout
    cancelled = False
    while not task.done():
        remaining = end - loop.time()
        if remaining <= 0:
            break
        try:
            await asyncio.wait((task,), timeout=remaining)
        except asyncio.CancelledError:
            cancelled = True  # finish first, re-raise below
    if task.done():
        error = task.exception() if not task.cancelled() else asyncio.CancelledError()
    else:
        task.cancel()
        # Retrieve its eventual outcome so asyncio does not warn about it.
        task.add_done_callback(lambda t: t.cancelled() or t.exception())
        error = TimeoutError(f"did not finish within {timeout} s")
    if cancelled:
        raise asyncio.CancelledError
    return error
