"""The server of a command that talks to the agents without a run: ``check``, ``fleet status``,
``fleet stop`` and ``calibrate`` (docs/fleet.md).

Such a command listens where the master would (the master file's host, port, secret and TLS):
the agents already connect there and retry with backoff while nobody listens. It admits the
robots it is about, asks each that connects and routes the answers back to the asker: a
:class:`~minimize_surprise.wire.CheckReport` by its ``seq``, a ``Pong`` by its ``seq``, a
``Result`` or ``Failed`` by its evaluation id, a ``Stopped`` to the command's
:class:`~master_service.stopall.Stopper`. One class for all of them, so that what one learns
(the port taken by a run, a check's timeout) every one gets.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import time
from collections.abc import Callable, Sequence
from typing import Any, Final

from master_service.config import MasterConfig
from master_service.rundir import RunDirError
from master_service.server import Answer, RobotServer, Session
from master_service.stopall import POLL_INTERVAL, Stopper
from minimize_surprise.wire import (
    REFUSED_UNKNOWN_ROBOT,
    Check,
    CheckReport,
    Evaluate,
    Failed,
    Ping,
    Pong,
    Result,
    Stopped,
    encode_payload,
)

__all__ = ["CHECK_TIMEOUT", "CONNECT_TIMEOUT", "PING_TIMEOUT", "AgentServer"]

#: Seconds a command waits for the agents to connect: an agent that found no master backs off up
#: to 30 s between tries (``reconnect.max``), so one that has waited long still comes within this.
CONNECT_TIMEOUT: Final = 40.0
#: Seconds an agent has to answer a check: its parts answer within 2 s each (read at once), the
#: battery and ``vcgencmd`` within 2 s more each.
CHECK_TIMEOUT: Final = 10.0
#: Seconds a ping may take before it counts as lost.
PING_TIMEOUT: Final = 2.0


class AgentServer:
    """Listens where the master would and asks each agent that connects.

    ``admit(robot_id)`` returns None or why the robot is refused; ``on_session(session)`` (a
    coroutine function, optional) runs as a task for every robot that joins, and :meth:`serve`
    waits for those tasks before it closes. ``purpose`` names the server's run id (``check``,
    ``fleet-status``, ...), which the agents log.
    """

    def __init__(
        self,
        config: MasterConfig,
        secret: bytes,
        log: logging.Logger,
        *,
        admit: Callable[[str], str | None],
        purpose: str,
        on_session: Callable[[Session], Any] | None = None,
    ) -> None:
        self.log = log
        self._admit_reason = admit
        self._on_session = on_session
        self._tasks: set[asyncio.Task[None]] = set()
        #: set for ``fleet stop``: the Stopped replies go to it
        self.stopper: Stopper | None = None
        self.joined = asyncio.Event()
        self._seq = 0
        self._pongs: dict[tuple[str, int], asyncio.Future[float]] = {}
        self._reports: dict[tuple[str, int], asyncio.Future[CheckReport]] = {}
        self._results: dict[tuple[str, int], asyncio.Future[Result | Failed]] = {}
        self.server = RobotServer(
            host=config.host,
            port=config.port,
            secret=secret,
            sensors=(),  # a robot lacking a sensor is reported, not refused unseen
            run_id=f"{purpose}-{time.strftime('%Y%m%d-%H%M%S')}",
            heartbeat_interval=config.heartbeat_interval,
            handshake_timeout=config.handshake_timeout,
            max_pending_connections=config.max_pending_connections,
            max_frame_size=config.max_frame_size,
            ssl_context=None if config.tls is None else _ssl(config),
            admit=self._admit,
            on_join=self._join,
            on_leave=lambda session, reason: None,
            on_message=self._on_message,
            on_pong=self._on_pong,
            logger=log,
        )

    def _admit(self, robot_id: str) -> tuple[str, str] | None:
        reason = self._admit_reason(robot_id)
        return None if reason is None else (REFUSED_UNKNOWN_ROBOT, reason)

    def _join(self, session: Session) -> None:
        if self._on_session is not None:
            task = asyncio.create_task(self._on_session(session), name=f"ask-{session.robot_id}")
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        self.joined.set()

    def _on_message(self, session: Session, msg: Answer) -> None:
        if isinstance(msg, Stopped):
            if self.stopper is not None:
                self.stopper.on_reply(session, msg)
            return
        if isinstance(msg, CheckReport):
            waiting: Any = self._reports.get((session.robot_id, msg.seq))
        elif isinstance(msg, Result | Failed):
            waiting = self._results.get((session.robot_id, msg.evaluation_id))
        else:
            return
        if waiting is not None and not waiting.done():
            waiting.set_result(msg)

    def _on_pong(self, session: Session, pong: Pong) -> None:
        future = self._pongs.get((session.robot_id, pong.seq))
        if future is not None and not future.done():
            future.set_result(time.monotonic())

    def next_seq(self) -> int:
        """A sequence number no earlier question of this server used."""
        self._seq += 1
        return self._seq

    # --- asking -------------------------------------------------------------------------------

    async def check(
        self, session: Session, seq: int | None = None
    ) -> tuple[CheckReport, float] | None:
        """The agent's check report and the laptop's wall-clock midpoint of the exchange; None
        when it did not answer within :data:`CHECK_TIMEOUT` (or its connection is gone)."""
        seq = self.next_seq() if seq is None else seq
        key = (session.robot_id, seq)
        future: asyncio.Future[CheckReport] = asyncio.get_running_loop().create_future()
        self._reports[key] = future
        sent = time.time()
        try:
            if self.server.send([session.robot_id], encode_payload(Check(seq=seq))):
                return None
            async with asyncio.timeout(CHECK_TIMEOUT):
                report = await future
        except TimeoutError:
            return None
        finally:
            del self._reports[key]
        return report, (sent + time.time()) / 2

    async def round_trip(self, session: Session, seq: int | None = None) -> float | None:
        """One ping's round trip in seconds, None when it got lost."""
        seq = self.next_seq() if seq is None else seq
        key = (session.robot_id, seq)
        future: asyncio.Future[float] = asyncio.get_running_loop().create_future()
        self._pongs[key] = future
        sent = time.monotonic()
        self.server.send([session.robot_id], encode_payload(Ping(seq=seq)))
        try:
            async with asyncio.timeout(PING_TIMEOUT):
                return await future - sent
        except TimeoutError:
            return None
        finally:
            del self._pongs[key]

    async def evaluate(
        self, session: Session, evaluate: Evaluate, timeout: float
    ) -> Result | Failed | None:
        """Have the agent run ``evaluate`` and wait for its Result (or Failed); None when none
        came within ``timeout`` seconds or the connection is gone."""
        key = (session.robot_id, evaluate.evaluation_id)
        future: asyncio.Future[Result | Failed] = asyncio.get_running_loop().create_future()
        self._results[key] = future
        try:
            if self.server.send([session.robot_id], encode_payload(evaluate)):
                return None
            async with asyncio.timeout(timeout):
                return await future
        except TimeoutError:
            return None
        finally:
            del self._results[key]

    # --- listening ----------------------------------------------------------------------------

    async def start(self) -> None:
        """Bind and accept; a port held by a running master is a :class:`RunDirError` saying
        so."""
        try:
            await self.server.bind()
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise RunDirError(
                    f"{self.server.host}:{self.server.requested_port} is taken: is a run "
                    "going? Its master holds the robots: `surprise-master fleet stop --run "
                    "RUN_DIR` stops them through it, `surprise-master status RUN_DIR` shows them"
                ) from exc
            raise
        await self.server.start_serving()

    async def close(self, reason: str) -> None:
        """Cancel what is still being asked and say goodbye to the agents."""
        for task in self._tasks:
            task.cancel()
        await self.server.close(reason)

    async def wait_for_robots(self, expected: Sequence[str] | int, timeout: float) -> None:
        """Until every expected robot (ids, or a count of any) is connected, or ``timeout``."""
        deadline = time.monotonic() + timeout
        while not self._complete(expected):
            left = deadline - time.monotonic()
            if left <= 0:
                return
            self.joined.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(left):
                    await self.joined.wait()

    def _complete(self, expected: Sequence[str] | int) -> bool:
        sessions = self.server.sessions
        if isinstance(expected, int):
            return len(sessions) >= expected
        return all(robot in sessions for robot in expected)

    async def serve(
        self, done: Callable[[], bool], timeout: float, on_listening: Any = None
    ) -> None:
        """Listen until ``done()`` or ``timeout`` seconds, then let the asked finish and close
        (``on_listening(port)`` once robots can connect)."""
        await self.start()
        try:
            if on_listening is not None:
                on_listening(self.server.port)
            deadline = time.monotonic() + timeout
            while not done():
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self.joined.clear()
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(min(left, POLL_INTERVAL)):
                        await self.joined.wait()
            if self._tasks:
                await asyncio.wait(set(self._tasks))
        finally:
            await self.close("fleet command done")


def _ssl(config: MasterConfig) -> Any:
    from master_service.config import build_ssl_context

    assert config.tls is not None
    return build_ssl_context(config.tls)
