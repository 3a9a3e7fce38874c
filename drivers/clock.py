"""The ``Clock`` seam: the control loop sleeps to absolute deadlines on an injected clock.

The real clock is :class:`MonotonicClock`; the simulator provides a lockstep clock whose time is the
shared world's time (see ``simulator``), so simulated runs go as fast as the CPU allows and repeat
exactly for a seed.
"""

from __future__ import annotations

import asyncio
import time
from abc import ABC, abstractmethod


class Clock(ABC):
    """Time for the control loop, in seconds."""

    @abstractmethod
    def now(self) -> float:
        """The current time in seconds (monotonic; the origin is arbitrary)."""

    @abstractmethod
    async def sleep_until(self, deadline: float) -> None:
        """Return once ``now() >= deadline`` (at once if it already is)."""


class MonotonicClock(Clock):
    """Wall-clock time from ``time.monotonic``; sleeps to absolute deadlines so periods never drift.

    ``asyncio.sleep`` on Linux wakes up to about one event-loop tick late; the last
    ``SPIN_MARGIN`` seconds before a deadline are therefore waited in short sleeps of zero, which
    keeps the period error well under a millisecond without blocking other tasks.
    """

    #: Below this remaining time, yield to the loop instead of sleeping (timer slack is ~1 ms).
    SPIN_MARGIN = 0.0015

    def now(self) -> float:
        return time.monotonic()

    async def sleep_until(self, deadline: float) -> None:
        remaining = deadline - time.monotonic()
        if remaining > self.SPIN_MARGIN:
            await asyncio.sleep(remaining - self.SPIN_MARGIN)
        while time.monotonic() < deadline:
            await asyncio.sleep(0)
