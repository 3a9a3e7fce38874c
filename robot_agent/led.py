"""The post-evaluation's start flash on the robot's top LED (docs/robot-agent.md).

An overhead camera's tracker aligns its video with the run by a colour flash: at the first step of
a post-evaluation every robot lights its top LED full green for :data:`FLASH_SECONDS`, then turns
it off, and the master writes when the post-evaluation began (``post_evaluation.json``).

The LED is a signal, never a safety part, so nothing here may stop or delay the control loop or
its safety layer: a write to a body that waits for I/O (a Thymio over D-Bus) runs in a task of its
own, after the previous write (so "off" never overtakes "on"), bounded by :data:`LED_TIMEOUT`; a
simulated body records at once, in the step the flash belongs to. A failure is logged once per
flash and the loop goes on.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Final

from drivers.body import Body
from drivers.clock import Clock

__all__ = ["FLASH_COLOUR", "FLASH_SECONDS", "LED_TIMEOUT", "OFF", "StartFlash"]

log = logging.getLogger(__name__)

#: Full green: the colour a camera finds most easily on the grey carpet and the Thymio's white
#: shell (the Thymio's 32 of 32).
FLASH_COLOUR: Final = (0.0, 1.0, 0.0)
OFF: Final = (0.0, 0.0, 0.0)
#: How long the flash shows, in the loop's seconds: five steps at 10 Hz, at least ten frames of
#: a 25 fps camera.
FLASH_SECONDS: Final = 0.5
#: Seconds one LED write may take: medulla answers a write itself, in milliseconds.
LED_TIMEOUT: Final = 0.25


class StartFlash:
    """One flash of ``body``'s top LED, driven by the control loop: :meth:`start` at its first
    step, :meth:`step` at every step after (turns it off once ``duration`` has passed on
    ``clock``), :meth:`finish` when the evaluation ends however it ends. None of them raises."""

    def __init__(
        self,
        body: Body,
        clock: Clock,
        *,
        duration: float = FLASH_SECONDS,
        logger: logging.Logger | logging.LoggerAdapter | None = None,
    ) -> None:
        self.body = body
        self.clock = clock
        self.duration = duration
        self.log = logger if logger is not None else log
        #: the loop's time until which the LED stays lit, None while it is off
        self.until: float | None = None
        #: the first failure of this flash, None while every write worked
        self.failure: str | None = None
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        """Light the LED now."""
        self.until = self.clock.now() + self.duration
        await self._write(FLASH_COLOUR)

    async def step(self) -> None:
        """Turn the LED off once its time is up (a cheap comparison on every other step)."""
        if self.until is not None and self.clock.now() >= self.until:
            self.until = None
            await self._write(OFF)

    async def finish(self) -> None:
        """Turn a lit LED off and wait for the last write, bounded (the evaluation ended
        early, or the loop's last steps came before the time was up)."""
        if self.until is not None:
            self.until = None
            await self._write(OFF)
        task, self._task = self._task, None
        if task is not None:
            # Bounded by each write's own timeout; the LED must not hold up an evaluation's end.
            with contextlib.suppress(Exception):
                await asyncio.wait((task,), timeout=2 * LED_TIMEOUT)

    async def _write(self, colour: tuple[float, float, float]) -> None:
        if not self.body.blocking:
            # A simulated body answers at once: recorded in the very step it belongs to.
            await self._set(colour)
            return
        previous = self._task
        self._task = asyncio.create_task(self._after(previous, colour), name="top-led")

    async def _after(
        self, previous: asyncio.Task[None] | None, colour: tuple[float, float, float]
    ) -> None:
        if previous is not None:
            with contextlib.suppress(BaseException):
                await previous
        await self._set(colour)

    async def _set(self, colour: tuple[float, float, float]) -> None:
        try:
            async with asyncio.timeout(LED_TIMEOUT):
                await self.body.set_top_led(*colour)
        except TimeoutError:
            self._failed(f"no answer within {LED_TIMEOUT} s")
        except NotImplementedError as exc:
            self._failed(str(exc) or "this body has no top LED")
        except Exception as exc:  # an LED is no reason to stop anything: say so and go on
            self._failed(f"{type(exc).__name__}: {exc}")

    def _failed(self, why: str) -> None:
        if self.failure is None:
            self.failure = why
            self.log.warning("the post-evaluation's start flash failed (%s); the run goes on", why)
