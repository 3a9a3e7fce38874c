"""Whether the robot can be reached, and getting it back when it cannot (docs/thymio.md).

A Thymio goes away (battery swap, USB glitch, switched on after the Pi booted), and asebamedulla
never reconnects to it by itself. The agent then must not pretend: evaluations fail with the
reason ``robot-unreachable`` (so the master repeats the round and says which robot), the log says
plainly when the robot was lost and when it is back, and a background task keeps calling
``body.recover()`` with capped backoff until the robot answers again (for a Thymio that ends the
medulla that lost it, and its service starts a fresh one).
"""

from __future__ import annotations

import asyncio
import logging
import random
import time
from collections.abc import Callable
from typing import Final

from drivers.body import Body
from minimize_surprise.backoff import Backoff, BackoffConfig
from robot_agent.bounded import finish
from robot_agent.loop import FAILED_UNREACHABLE

__all__ = ["FAILED_UNREACHABLE", "RECOVERY_BACKOFF", "RECOVER_TIMEOUT", "RobotHealth"]

log = logging.getLogger(__name__)
#: Seconds one recovery attempt may take: connecting to D-Bus, a few calls to medulla and two
#: reads from the robot (each bounded by the driver's own call timeout), with room to spare.
RECOVER_TIMEOUT: Final = 10.0
#: Pauses between recovery attempts: quick at first (a medulla restarted under us is back within
#: a second or two), then every 10 s at most, which also paces how often a medulla that cannot
#: find the robot is restarted.
RECOVERY_BACKOFF: Final = BackoffConfig(initial=1.0, max=10.0, jitter=0.25)


class RobotHealth:
    """Tracks whether ``body`` is reachable and recovers it in :meth:`run` (a background task).

    :meth:`lost` marks it unreachable (logged once); :attr:`reachable` and :meth:`failure` tell
    the evaluation runner whether to run at all. ``backoff`` paces the recovery attempts;
    ``clock`` is for the "since" in messages.
    """

    def __init__(
        self,
        body: Body,
        *,
        rng: random.Random | None = None,
        backoff: BackoffConfig = RECOVERY_BACKOFF,
        logger: logging.Logger | logging.LoggerAdapter | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.body = body
        self.log = logger or log
        self._clock = clock
        self._backoff = Backoff(backoff, rng)
        self._reason: str | None = None
        self._since = 0.0
        self._lost = asyncio.Event()
        self._back = asyncio.Event()
        self._back.set()
        #: Times the robot was lost, and recovered.
        self.losses = 0
        self.recoveries = 0

    @property
    def reachable(self) -> bool:
        """Whether the robot is believed reachable."""
        return self._reason is None

    def failure(self) -> str:
        """The Failed reason for an evaluation asked for while the robot is unreachable."""
        down = self._clock() - self._since
        return f"{FAILED_UNREACHABLE}: for {down:.1f} s: {self._reason}"

    def lost(self, reason: str) -> None:
        """The robot cannot be reached (``reason`` says how it showed); recovery starts."""
        if self._reason is not None:
            return
        self._reason = reason
        self._since = self._clock()
        self.losses += 1
        self._back.clear()
        self._lost.set()
        self.log.warning(
            "robot unreachable: %s; evaluations fail until it is back, recovering in the "
            "background",
            reason,
        )

    async def wait_reachable(self) -> None:
        """Return once the robot is reachable."""
        await self._back.wait()

    async def run(self) -> None:
        """Recover the body whenever it was lost; runs until cancelled."""
        while True:
            await self._lost.wait()
            error = await finish(self.body.recover(), RECOVER_TIMEOUT)
            if error is None:
                self.log.info("robot reachable again after %.1f s", self._clock() - self._since)
                self._reason = None
                self.recoveries += 1
                self._backoff.reset()
                self._lost.clear()
                self._back.set()
                continue
            delay = self._backoff.next_delay()
            # Evaluations refused meanwhile say why the robot is still out of reach (a bus that
            # is not there, medulla not running), not only how it was lost.
            self._reason = str(error) or type(error).__name__
            # The first failure says why; later ones only in the debug log (every 10 s forever).
            level = logging.INFO if self._backoff.attempts == 1 else logging.DEBUG
            self.log.log(level, "robot still unreachable (%s); next try in %.1f s", error, delay)
            await asyncio.sleep(delay)
