"""``surprise-master fleet stop``: every robot's motors stopped now, through the agents
(docs/fleet.md).

The robot's side: a :class:`~minimize_surprise.wire.StopAll` (sent only to agents offering the
``stop`` feature) makes the agent's watchdog stop the motors at once, cancels the running
evaluation and answers :class:`~minimize_surprise.wire.Stopped` once the robot itself confirmed
the stop; the agent never refuses one. :class:`Stopper` sends it and waits for the answers.

Without a run the fleet command serves the agents itself (:func:`master_service.fleet.fleet_stop`).
While a run is going its master holds the port and the agents' sessions, so the stop goes
through it (``fleet stop --run DIR``): :func:`request_stop` drops a
:class:`~runfiles.schema.StopRequest` into the run's ``requests/``; the master's
:class:`StopDesk` takes it within :data:`POLL_INTERVAL`, fails the running attempt (it does not
count), pauses the run with a line naming the stop (:data:`STOP_PAUSE_TEXT`), sends every
connected robot the StopAll and appends a ``fleet-stop`` event with the robots that confirmed and
those that did not answer, which the command prints. ``surprise-master continue`` lets the run go
on; its next Evaluate is the robots' go-on.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Final

from master_service import desk
from master_service.desk import new_token
from master_service.rundir import RunDir
from master_service.server import RobotServer, Session
from minimize_surprise.wire import FEATURE_STOP, StopAll, Stopped, encode_payload, printable
from runfiles.schema import (
    EVENT_FLEET_STOP,
    Event,
    StopRequest,
)

__all__ = [
    "POLL_INTERVAL",
    "STOP_ANSWER_TIMEOUT",
    "STOP_PAUSE_TEXT",
    "STOP_REPLY_TIMEOUT",
    "StopDesk",
    "StopOutcome",
    "Stopper",
    "format_stop",
    "request_stop",
]

#: Seconds an agent has to confirm a stop: the watchdog's stop at once, then the cancelled
#: evaluation's clean-up (its motor stop, 0.5 s, waited for up to four times that) and the
#: confirming stop itself, with room for a busy Wi-Fi.
STOP_REPLY_TIMEOUT: Final = 5.0
#: Seconds between two looks of the master's desk into ``requests/``: one ``scandir`` each, far
#: below a person's reaction.
POLL_INTERVAL: Final = 0.25
#: Seconds ``fleet stop --run`` waits for the master's event: its poll and every robot's answer,
#: with room for a busy laptop.
STOP_ANSWER_TIMEOUT: Final = POLL_INTERVAL + STOP_REPLY_TIMEOUT + 5.0
#: What the run's pause says (``pause.json``, the master's log).
STOP_PAUSE_TEXT: Final = "stopped by `surprise-master fleet stop`: every robot's motors are stopped"


@dataclass
class StopOutcome:
    """What ``fleet stop`` achieved: the robots that confirmed their motors stopped, and those
    that did not (with why, one line each)."""

    confirmed: list[str] = field(default_factory=list)
    unanswered: dict[str, str] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        """Whether every robot confirmed."""
        return not self.unanswered


class Stopper:
    """Sends StopAll to sessions and waits for their Stopped; shared by the fleet command's own
    server (:mod:`master_service.fleet`) and the master's :class:`StopDesk`."""

    def __init__(self, server: RobotServer, log: logging.Logger, reason: str) -> None:
        self.server = server
        self.log = log
        self.reason = reason
        self._seq = 0
        self._waiting: dict[tuple[str, int], asyncio.Future[Stopped]] = {}

    def on_reply(self, session: Session, msg: Stopped) -> None:
        """A robot's Stopped; one nobody waits for (late, unasked) is ignored."""
        future = self._waiting.get((session.robot_id, msg.seq))
        if future is not None and not future.done():
            future.set_result(msg)

    async def stop(self, session: Session) -> str | None:
        """Stop ``session``'s robot; None when it confirmed, else why not (one line)."""
        robot = session.robot_id
        if FEATURE_STOP not in session.hello.features:
            version = printable(session.hello.software_version)
            return (
                f"its agent (software {version}) predates the fleet stop and cannot confirm "
                "one: update it"
            )
        self._seq += 1
        key = (robot, self._seq)
        future: asyncio.Future[Stopped] = asyncio.get_running_loop().create_future()
        self._waiting[key] = future
        try:
            message = StopAll(seq=self._seq, reason=self.reason)
            if self.server.send([robot], encode_payload(message)):
                return "its session ended before the stop could be sent"
            try:
                async with asyncio.timeout(STOP_REPLY_TIMEOUT):
                    reply = await future
            except TimeoutError:
                return f"no answer to the stop within {STOP_REPLY_TIMEOUT:g} s"
        finally:
            del self._waiting[key]
        if not reply.confirmed:
            return f"the robot did not confirm the stop: {printable(reply.detail)}"
        if reply.evaluation_id is not None:
            self.log.warning("%s: evaluation %d cancelled, motors stopped", robot,
                             reply.evaluation_id)  # fmt: skip
        return None


def request_stop(run_dir: RunDir, *, timeout: float = STOP_ANSWER_TIMEOUT) -> Event:
    """Ask the master running ``run_dir`` to stop every robot and pause; its ``fleet-stop``
    event. Raises :class:`RunDirError` when no master runs the run or none answers in time (the
    request is then taken back: a stop that fires late would pause a run nobody watches)."""
    not_running = (
        f"no master is running {run_dir.path}: stop the fleet without --run (the command then "
        "serves the agents itself)"
    )
    request = StopRequest(token=new_token(), requested_at=time.time())
    return desk.ask_master(
        run_dir.path, request, EVENT_FLEET_STOP, timeout=timeout, not_running=not_running
    )


class StopDesk:
    """The master's side of ``fleet stop --run``: takes the requests in ``requests/`` and
    answers each with a ``fleet-stop`` event. :meth:`run` until cancelled; :meth:`on_reply`
    gets the robots' Stopped from the server.

    ``members()`` names the run's robots (those not connected are reported unanswered);
    ``on_stop()`` is called first, before any robot is told: the master fails its running
    attempt and pauses before the next one.
    """

    def __init__(
        self,
        run_dir: RunDir,
        server: RobotServer,
        log: logging.Logger,
        *,
        members: Callable[[], Iterable[str]],
        on_stop: Callable[[], None],
    ) -> None:
        self.run_dir = run_dir
        self.server = server
        self.log = log
        self._members = members
        self._on_stop = on_stop
        self.stopper = Stopper(server, log, "surprise-master fleet stop (the run pauses)")

    def on_reply(self, session: Session, msg: Stopped) -> None:
        """A robot's Stopped."""
        self.stopper.on_reply(session, msg)

    async def run(self) -> None:
        """Answer requests until cancelled, in the order they came."""
        # The interval read at each look: tests shorten it.
        await desk.serve_requests(
            self.run_dir.path, StopRequest, self.handle, self.log, "the fleet stop",
            lambda: POLL_INTERVAL,
        )  # fmt: skip

    async def handle(self, request: StopRequest) -> Event:
        """Stop every robot connected now, pause the run; the event that says how it went."""
        self.log.warning("fleet stop: every robot's motors stop now; the run pauses")
        self._on_stop()
        sessions = list(self.server.sessions.values())
        answers = await asyncio.gather(*(self.stopper.stop(s) for s in sessions))
        outcome = StopOutcome()
        for session, why in zip(sessions, answers, strict=True):
            if why is None:
                outcome.confirmed.append(session.robot_id)
            else:
                outcome.unanswered[session.robot_id] = why
        for robot in self._members():
            if robot not in outcome.confirmed and robot not in outcome.unanswered:
                outcome.unanswered[robot] = "not connected to the run's master"
        detail = "; ".join(f"{robot}: {why}" for robot, why in outcome.unanswered.items())
        if outcome.unanswered:
            self.log.error("fleet stop: not confirmed by %s", detail)
        return Event(
            time=time.time(),
            kind=EVENT_FLEET_STOP,
            request=request.token,
            accepted=outcome.complete,
            detail=detail,
            confirmed=sorted(outcome.confirmed),
            unanswered=sorted(outcome.unanswered),
        )


def format_stop(outcome: StopOutcome) -> str:
    """The stop's outcome for a person: who confirmed, who did not and why."""
    lines = [
        "stopped (confirmed): " + (", ".join(outcome.confirmed) or "none"),
        "did not answer: " + (", ".join(outcome.unanswered) or "none"),
    ]
    lines += [f"  {robot}: {why}" for robot, why in outcome.unanswered.items()]
    return "\n".join(lines)
