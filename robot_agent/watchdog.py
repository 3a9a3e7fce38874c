"""The watchdog: stop the motors within 300 ms when the control loop stalls (docs/robot-agent.md).

The Thymio keeps driving at its last motor targets until told otherwise, so a control loop that
hangs (a sensor read that never returns, a bug, a lost master the loop waits for) would leave the
robot driving blind. The control loop calls :meth:`Watchdog.feed` every step; a background task
checks every :data:`CHECK_PERIOD` seconds and, once no feed came for more than :data:`TIMEOUT`
seconds, awaits the ``stop`` coroutine given at construction (normally ``body.stop``).

Timing guarantee (defaults): the loop is last fed at t0; the first check after t0 + TIMEOUT comes
at most CHECK_PERIOD later, so the stop is issued by t0 + 0.25 + 0.025 = t0 + 0.275 s, which
leaves 25 ms of the 300 ms limit (:data:`MAX_STOP_DELAY`) for event-loop lateness (about 1 ms on
Linux) and the motor write itself (a no-reply D-Bus call). The constructor refuses settings whose
``timeout + period`` exceeds that limit.

Limits: the watchdog is a task on the agent's event loop, so it cannot fire while that loop is
blocked by synchronous code (which is why blocking I2C stays off the loop); a blocked loop or a dead
Pi is covered by the optional Aseba failsafe on the Thymio itself.

Once tripped (by expiry or :meth:`Watchdog.trip`), the watchdog stays tripped, ignores feeds and
retries a failed or hung stop until it succeeds, at first on the next check and then with pauses
doubling up to :data:`RETRY_MAX` (a robot that went away would otherwise get 40 stop attempts, and
some 160 D-Bus messages, a second for as long as it is gone); :meth:`Watchdog.arm` starts afresh.
The control loop must check :attr:`Watchdog.tripped` before it drives, and end the evaluation with
:attr:`Watchdog.tripped_reason` if it is set.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from types import TracebackType
from typing import Self

from minimize_surprise.backoff import Backoff, BackoffConfig

log = logging.getLogger(__name__)

#: No feed for this long (seconds) trips the watchdog: a 10 Hz loop feeds every 0.1 s, so this
#: allows one missed step plus 50 ms of jitter before the robot is considered out of control.
TIMEOUT = 0.25
#: How often the background task checks (seconds): TIMEOUT + CHECK_PERIOD = 0.275 s stays inside
#: MAX_STOP_DELAY with 25 ms to spare for scheduling lateness and the stop call.
CHECK_PERIOD = 0.025
#: The requirement: motors stop at most this long (seconds) after the last feed.
MAX_STOP_DELAY = 0.3
#: How long one stop attempt may take (seconds) before it is abandoned, logged and retried; a D-Bus
#: call to a vanished robot never returns on its own (docs/thymio.md).
STOP_TIMEOUT = 0.5

#: The longest pause (seconds) between retries of a stop that keeps failing: a robot that does not
#: answer still gets a stop attempt every second, in case it comes back.
RETRY_MAX = 1.0

#: ``tripped_reason`` when the loop stopped feeding.
REASON_STALL = "stall"


def _retrieve(task: asyncio.Future[object]) -> None:
    # An abandoned stop attempt may still end in an error; fetch it so asyncio does not warn that
    # the exception was never retrieved.
    if not task.cancelled():
        task.exception()


class Watchdog:
    """Stops the motors when the control loop stops feeding it; use as an async context manager.

    ``stop`` is a coroutine function that stops the motors (``body.stop``). ``now`` and ``sleep``
    are the time source and sleep of the check loop; real robots want the defaults (wall time),
    because a simulated clock stalls together with the loop it should watch. The watchdog starts
    disarmed unless ``armed`` is True.
    """

    def __init__(
        self,
        stop: Callable[[], Awaitable[object]],
        *,
        timeout: float = TIMEOUT,
        period: float = CHECK_PERIOD,
        stop_timeout: float = STOP_TIMEOUT,
        now: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], Awaitable[object]] = asyncio.sleep,
        armed: bool = False,
    ) -> None:
        if not (timeout > 0 and period > 0 and stop_timeout > 0):
            raise ValueError("timeout, period and stop_timeout must be positive")
        if timeout + period > MAX_STOP_DELAY:
            raise ValueError(
                f"timeout + period = {timeout + period:.3f} s exceeds the {MAX_STOP_DELAY} s limit"
            )
        self._stop = stop
        self._timeout = timeout
        self._period = period
        self._stop_timeout = stop_timeout
        self._now = now
        self._sleep = sleep
        self._armed = armed
        self._last_feed = now()
        self._tripped_reason: str | None = None
        self._stopped = False  # whether a stop succeeded since the trip
        # Pauses between retries of a failing stop: ``period`` doubling up to RETRY_MAX. Its
        # ``attempts`` counts the failed stops since the trip, to log the first one loudly.
        self._retry_backoff = Backoff(BackoffConfig(initial=period, max=RETRY_MAX, jitter=0.0))
        self._next_retry = 0.0  # when a failed stop may be tried again (on ``now``)
        # Bumped by arm(): a stop attempt that began before it says nothing about the new arming.
        self._epoch = 0
        self._lock = asyncio.Lock()  # one stop attempt at a time (expiry and trip() may race)
        self._task: asyncio.Task[None] | None = None

    # ------------------------------------------------------------------ state

    @property
    def armed(self) -> bool:
        """Whether a missing feed trips the watchdog."""
        return self._armed

    @property
    def tripped(self) -> bool:
        """Whether the watchdog has tripped since it was last armed."""
        return self._tripped_reason is not None

    @property
    def tripped_reason(self) -> str | None:
        """Why it tripped (:data:`REASON_STALL` or the reason given to :meth:`trip`), else None."""
        return self._tripped_reason

    @property
    def stopped(self) -> bool:
        """Whether a stop has succeeded since the trip (False while retrying a failing stop)."""
        return self._stopped

    # ------------------------------------------------------------------ control-loop interface

    def feed(self) -> None:
        """Tell the watchdog the loop is alive; call once per step after the motors were set."""
        if self._tripped_reason is None:
            self._last_feed = self._now()

    def arm(self) -> None:
        """Start watching (at the start of an evaluation); clears an earlier trip and feeds."""
        self._tripped_reason = None
        self._stopped = False
        self._retry_backoff.reset()
        self._next_retry = 0.0
        self._epoch += 1
        self._last_feed = self._now()
        self._armed = True

    def disarm(self) -> None:
        """Stop watching, for when the motors are already stopped (between evaluations)."""
        self._armed = False

    async def trip(self, reason: str) -> bool:
        """Stop the motors now (lost link, repeated read failures) and record ``reason``.

        The first reason since :meth:`arm` is kept. Returns whether the motors are known to be
        stopped; a failed stop is retried by the background task.
        """
        if self._tripped_reason is None:
            self._tripped_reason = reason
            log.warning("watchdog tripped (%s): stopping the motors", reason)
        self._armed = False
        return await self._stop_motors()

    # ------------------------------------------------------------------ lifecycle

    async def __aenter__(self) -> Self:
        if self._task is not None:
            raise RuntimeError("the watchdog is already running")
        self._last_feed = self._now()
        self._task = asyncio.create_task(self._run(), name="watchdog")
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            try:
                await task
            except asyncio.CancelledError:
                # Our own cancellation of the task; re-raise only if *we* are being cancelled.
                current = asyncio.current_task()
                if current is not None and current.cancelling():
                    raise

    # ------------------------------------------------------------------ internals

    async def _run(self) -> None:
        while True:
            await self._sleep(self._period)
            try:
                await self._check()
            except Exception:  # a bug here must not end the watching
                log.exception("watchdog check failed; still watching")

    async def _check(self) -> None:
        if self._tripped_reason is not None:
            if not self._stopped and self._now() >= self._next_retry:
                await self._stop_motors()  # retry a stop that failed or hung
            return
        if not self._armed:
            return
        silent = self._now() - self._last_feed
        if silent > self._timeout:
            self._tripped_reason = REASON_STALL
            self._armed = False
            log.error(
                "watchdog: control loop stalled, no feed for %.3f s (limit %.3f s); "
                "stopping the motors",
                silent,
                self._timeout,
            )
            await self._stop_motors()

    async def _stop_motors(self) -> bool:
        async with self._lock:
            if self._tripped_reason is None:  # re-armed while this waited for the lock
                return False
            if self._stopped:
                return True
            epoch = self._epoch
            error = await self._attempt_stop()
            if error is None:
                # Only for the arming it began in: the motors may have been driven since arm().
                self._stopped = epoch == self._epoch
                failures = self._retry_backoff.attempts
                if failures:
                    log.info("watchdog: motors stopped after %d failed attempts", failures)
                self._retry_backoff.reset()
                return True
            self._next_retry = self._now() + self._retry_backoff.next_delay()
            # Loud once, then quiet: a vanished robot would otherwise log a line a second.
            level = logging.ERROR if self._retry_backoff.attempts == 1 else logging.DEBUG
            log.log(level, "watchdog: stopping the motors failed (%s); retrying", error)
            return False

    async def _attempt_stop(self) -> str | None:
        """One bounded call of ``stop``: None on success, else what went wrong."""
        try:
            stop_task = asyncio.ensure_future(self._stop())
        except Exception as exc:  # ``stop`` raised before returning an awaitable
            return repr(exc)
        # The limit runs on the injected sleep, so tests can drive it with fake time.
        timer = asyncio.ensure_future(self._sleep(self._stop_timeout))
        try:
            await asyncio.wait((stop_task, timer), return_when=asyncio.FIRST_COMPLETED)
        finally:
            timer.cancel()
            if not stop_task.done():
                # Abandon it rather than await it: a call that ignores cancellation would hang us.
                stop_task.cancel()
                stop_task.add_done_callback(_retrieve)
        if not stop_task.done():
            return f"no answer within {self._stop_timeout} s"
        if stop_task.cancelled():
            return "the stop call was cancelled"
        error = stop_task.exception()
        return None if error is None else repr(error)
