"""The agent of one robot: a body, a clock and a link to the master, run until cancelled.

Its tasks: the link to the master (which starts evaluations), the watchdog, and the recovery of
the robot when it cannot be reached (:class:`~robot_agent.health.RobotHealth`).

::

    async with body, Agent(config, body, clock, secret) as agent:
        await agent.run()          # until cancelled

Several agents can share one event loop (the master's ``sim`` command runs N of them with simulated
bodies over loopback TCP): an Agent holds no global state and installs no signal handlers; the
composition root (``robot_agent.cli``) does that. The agent does not open or close the body (its
owner does) but it stops the motors when it ends, whatever the reason.

With ``telemetry.broker`` configured, the agent also runs a
:class:`~telemetry.publisher.TelemetryPublisher` (its own background task, outside the task group:
telemetry failing never stops the agent) that publishes evaluation summaries and step samples.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import time
from collections.abc import Callable
from types import TracebackType
from typing import Final, Self

from drivers.body import Body
from drivers.clock import Clock, MonotonicClock
from minimize_surprise.safety import safety_seed
from minimize_surprise.warmup import warm_up_control
from robot_agent.config import AgentConfig, make_ssl_context
from robot_agent.health import RobotHealth
from robot_agent.link import Link, robot_logger
from robot_agent.runner import EvaluationRunner, stop_motors
from robot_agent.watchdog import Watchdog
from telemetry.payloads import robot_suffix
from telemetry.publisher import TelemetryPublisher
from telemetry.robot import RobotTelemetry

__all__ = ["WARM_UP_NOTE", "Agent"]

#: Seconds of compiling at start-up worth a log line (a cached install takes milliseconds).
WARM_UP_NOTE: Final = 0.5


def _watchdog_time(clock: Clock) -> Callable[[], float]:
    """The time the watchdog measures silence in: the time the motors run in.

    A real robot drives in wall time, so the watchdog uses ``time.monotonic`` (never the loop's
    clock, which could stall together with the loop it watches). A simulated robot only moves
    while simulated time passes, and in lockstep its loop legitimately waits in wall time for the
    other robots' steps; on wall time the watchdog would trip there for nothing.
    """
    return time.monotonic if isinstance(clock, MonotonicClock) else clock.now


class Agent:
    """One robot's agent: watchdog, evaluation runner and link, as named tasks in a TaskGroup.

    With a simulated body pass the body's own clock (``SimBody.clock``); the watchdog then
    measures the simulated time (see :func:`_watchdog_time`).

    ``secret`` is the shared secret (see :func:`robot_agent.config.read_secret`); ``rng`` makes
    the reconnection jitter reproducible in tests. Use as an async context manager (which starts
    the tasks) and ``await agent.run()`` inside it, or just ``await agent.run()``, which enters
    the context itself. Leaving the context cancels the tasks and stops the motors. A TLS
    configuration whose files cannot be loaded raises :class:`~minimize_surprise.errors.ConfigError`
    here.
    """

    def __init__(
        self,
        config: AgentConfig,
        body: Body,
        clock: Clock,
        secret: bytes,
        *,
        rng: random.Random | None = None,
    ) -> None:
        self.config = config
        self.body = body
        self.clock = clock
        self.watchdog = Watchdog(
            body.stop, stop_timeout=config.loop.stop_timeout, now=_watchdog_time(clock)
        )
        #: whether the robot can be reached, and its recovery when it cannot
        self.health = RobotHealth(
            body,
            rng=rng,
            logger=robot_logger(logging.getLogger("robot_agent.health"), config.robot_id),
        )
        self._log = robot_logger(logging.getLogger("robot_agent.agent"), config.robot_id)
        #: the MQTT publisher, when a broker is configured
        self.telemetry: TelemetryPublisher | None = None
        robot_telemetry = None
        if config.telemetry is not None and config.telemetry.enabled:
            self.telemetry = TelemetryPublisher(
                config.telemetry,
                status_suffix=robot_suffix(config.robot_id, "status"),
                # Stable per robot: a restarted agent takes over its old session on the broker.
                client_id=f"surprise-{config.robot_id}",
                name=f"telemetry[{config.robot_id}]",
            )
            robot_telemetry = RobotTelemetry(self.telemetry, config.robot_id)
        self.runner = EvaluationRunner(
            body,
            clock,
            loop=config.loop,
            safety=config.safety,
            watchdog=self.watchdog,
            # Stable per robot, different between robots: their escape turns should not agree.
            safety_seed=safety_seed(config.robot_id),
            telemetry=robot_telemetry,
            health=self.health,
        )
        self.link = Link(
            config,
            secret,
            self.runner,
            body.sensors,
            watchdog=self.watchdog,
            rng=rng,
            ssl_context=make_ssl_context(config),
            read_firmware=body.read_firmware,
        )
        self._stack: contextlib.AsyncExitStack | None = None
        self._link_task: asyncio.Task[None] | None = None
        self._health_task: asyncio.Task[None] | None = None

    @property
    def connected(self) -> asyncio.Event:
        """Set while the master has welcomed this robot."""
        return self.link.connected

    async def __aenter__(self) -> Self:
        if self._stack is not None:
            raise RuntimeError("the agent is already running")
        stack = contextlib.AsyncExitStack()
        await stack.__aenter__()
        try:
            await stack.enter_async_context(self.watchdog)
            # Compiled now, not at the first step of the first evaluation, where it made a
            # swarm's first round miss its deadline (a thread: the watchdog keeps running).
            seconds = await asyncio.to_thread(warm_up_control, self.body.sensors)
            if seconds >= WARM_UP_NOTE:
                self._log.info("compiled the control step in %.1f s", seconds)
            group = await stack.enter_async_context(asyncio.TaskGroup())
            # Evaluations are children of the group too, so none outlives the agent.
            self.link.spawn = group.create_task
            self._link_task = group.create_task(
                self.link.run(), name=f"link[{self.config.robot_id}]"
            )
            self._health_task = group.create_task(
                self.health.run(), name=f"recovery[{self.config.robot_id}]"
            )
            if self.telemetry is not None:
                self.telemetry.start()  # connects in the background; returns at once
        except BaseException:
            await stack.aclose()
            raise
        self._stack = stack
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> bool | None:
        stack, self._stack = self._stack, None
        for task in (self._link_task, self._health_task):
            if task is not None:
                task.cancel()  # the group would otherwise wait for it forever
        self._link_task = self._health_task = None
        try:
            if stack is not None:
                return await stack.__aexit__(exc_type, exc, tb)
            return None
        finally:
            try:
                # The link's clean-up already stopped a running evaluation; this covers every
                # other way out (an error in the group, a cancellation between steps).
                await stop_motors(self.body, self.config.loop.stop_timeout)
            finally:
                # After the motors, so a slow broker never delays the stop (the close is
                # bounded by telemetry.publisher.CLOSE_TIMEOUT anyway).
                if self.telemetry is not None:
                    await self.telemetry.aclose()

    async def run(self) -> None:
        """Serve the master until cancelled (entering the context first if not done yet)."""
        if self._stack is None:
            async with self:
                await self.run()
            return
        # Everything happens in the group's tasks; this task only keeps the context open. If a
        # task fails, the group cancels this task and __aexit__ raises the error.
        await asyncio.get_running_loop().create_future()
