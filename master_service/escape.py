"""The experimenter's hand: ``surprise-master escape RUN_DIR ROBOT`` (docs/safety.md, paper Sec.
V-C: "if necessary, the experimenter will trigger the escape behavior to force robots back into
the arena").

A person's action reaches a running master through its run directory, as a pause's end does
(:mod:`master_service.pause`): the command drops an :class:`~runfiles.schema.EscapeRequest` into
``requests/`` (:func:`request_escape`), the master's :class:`EscapeDesk` takes it within
:data:`POLL_INTERVAL`, checks it, sends the robot an ``Escape`` message and appends an
:class:`~runfiles.schema.Event` with the outcome to ``events.jsonl``; the command waits for
that event and prints it. The robot's agent hands the request to its safety layer, which starts
its own bounded escape manoeuvre at its next control step (reason ``experimenter``): the message
carries no command, and the layer refuses it in the ``stop`` profile, which has no escape.

Refused, each with one line: a robot not in the run's swarm; a paused run (the robots stand still
for a person); a robot not connected; a robot whose agent predates the message (its Hello offers
no ``escape`` feature, and it would close the session on an unknown message); no evaluation
running within :data:`EVALUATION_WAIT` (the run waits for robots); the robot's own refusal; no
answer within :data:`REPLY_TIMEOUT`.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Sequence
from typing import Final

from master_service import desk
from master_service.desk import new_token
from master_service.rundir import RunDir, RunDirError
from master_service.server import RobotServer, Session
from minimize_surprise.wire import (
    ESCAPE_REFUSED_IDLE,
    FEATURE_ESCAPE,
    Escape,
    EscapeReply,
    encode_payload,
    is_valid_robot_id,
    printable,
)
from runfiles.schema import (
    EVENT_ESCAPE,
    EscapeRequest,
    Event,
)

__all__ = [
    "ANSWER_TIMEOUT",
    "EVALUATION_WAIT",
    "POLL_INTERVAL",
    "REPLY_TIMEOUT",
    "EscapeDesk",
    "drop_request",
    "escape_from_console",
    "request_escape",
]

#: Seconds between two looks into ``requests/``: far below a person's reaction, one
#: ``scandir`` each.
POLL_INTERVAL: Final = 0.25
#: Seconds the master waits for an evaluation to run on the robot (the moment between two
#: evaluations, a commit): a robot stands still between evaluations, with nothing to escape in.
EVALUATION_WAIT: Final = 5.0
#: Seconds the robot has to answer an Escape: it answers at once, from its event loop.
REPLY_TIMEOUT: Final = 2.0
#: Seconds the command waits for the master's answer: its poll, the wait for an evaluation and
#: the robot's answer, with room for a busy laptop.
ANSWER_TIMEOUT: Final = POLL_INTERVAL + EVALUATION_WAIT + REPLY_TIMEOUT + 5.0


def drop_request(run_dir: RunDir, robot: str) -> EscapeRequest:
    """Drop a request for ``robot``'s escape into ``run_dir``'s ``requests/`` for the master's
    desk; the request. Raises :class:`RunDirError` for a robot id no robot can have."""
    if not is_valid_robot_id(robot):
        raise RunDirError(f"{robot!r} is not a robot id (letters, digits, '.', '_', '-')")
    request = EscapeRequest(robot=robot, token=new_token(), requested_at=time.time())
    desk.drop_request(run_dir.path, request)
    return request


def escape_from_console(run_dir: RunDir, log: logging.Logger) -> Callable[[str], None]:
    """What an ``escape ROBOT`` line on the master's terminal does
    (:class:`~master_service.console.Console`): the request ``surprise-master escape`` drops;
    the desk answers it in the log."""

    def escape(robot: str) -> None:
        try:
            drop_request(run_dir, robot)
        except (RunDirError, OSError) as exc:
            log.warning("the experimenter's escape for %s: %s", robot, exc)
        else:
            log.info("the experimenter's escape for %s asked from the console", robot)

    return escape


def request_escape(run_dir: RunDir, robot: str, *, timeout: float = ANSWER_TIMEOUT) -> Event:
    """Ask the master running ``run_dir`` to make ``robot`` escape now; its answer (an
    ``escape`` event: ``accepted``, or why not in ``detail``).

    Raises :class:`RunDirError` when no master runs the run (``master_alive``), for a robot id
    no robot can have, or when the master does not answer within ``timeout`` (the request is
    then taken back, so that it never fires late).
    """
    if not is_valid_robot_id(robot):
        raise RunDirError(f"{robot!r} is not a robot id (letters, digits, '.', '_', '-')")
    request = EscapeRequest(robot=robot, token=new_token(), requested_at=time.time())
    not_running = (
        f"no master is running {run_dir.path}: the experimenter's escape reaches robots only "
        "during a run"
    )
    return desk.ask_master(
        run_dir.path, request, EVENT_ESCAPE, timeout=timeout, not_running=not_running
    )


class EscapeDesk:
    """The master's side: takes the requests in ``run_dir``'s ``requests/`` and answers each
    with an ``escape`` event (see the module docstring). :meth:`run` until cancelled;
    :meth:`on_reply` gets the robots' :class:`EscapeReply` messages from the server.

    ``members()`` names the robots of the run (the swarm once fixed, else those allowed or
    connected); ``paused()`` why the run waits for a person, None while it runs;
    ``evaluating(robot)`` whether that robot runs an evaluation it has not answered yet.
    """

    def __init__(
        self,
        run_dir: RunDir,
        server: RobotServer,
        log: logging.Logger,
        *,
        members: Callable[[], Sequence[str]],
        paused: Callable[[], str | None],
        evaluating: Callable[[str], bool],
    ) -> None:
        self.run_dir = run_dir
        self.server = server
        self.log = log
        self._members = members
        self._paused = paused
        self._evaluating = evaluating
        self._seq = 0
        self._waiting: dict[tuple[str, int], asyncio.Future[EscapeReply]] = {}

    async def run(self) -> None:
        """Answer requests until cancelled, one after the other in the order they came."""
        # The interval read at each look: tests shorten it.
        await desk.serve_requests(
            self.run_dir.path, EscapeRequest, self.handle, self.log,
            "the experimenter's escape", lambda: POLL_INTERVAL,
        )  # fmt: skip

    def on_reply(self, session: Session, msg: EscapeReply) -> None:
        """A robot's answer to an Escape; one nobody waits for (late, unasked) is ignored."""
        future = self._waiting.get((session.robot_id, msg.seq))
        if future is not None and not future.done():
            future.set_result(msg)
        else:
            self.log.debug("robot %s: an unasked escape reply ignored", session.robot_id)

    async def handle(self, request: EscapeRequest) -> Event:
        """Pass ``request`` on to its robot; the event that says how it went."""
        robot = request.robot
        accepted, evaluation_id, detail = await self._forward(robot)
        if accepted:
            self.log.warning(
                "the experimenter's escape: robot %s escapes now (evaluation %d)",
                robot,
                evaluation_id,
            )
        else:
            self.log.warning("the experimenter's escape for robot %s refused: %s", robot, detail)
        return Event(
            time=time.time(),
            kind=EVENT_ESCAPE,
            robot=robot,
            request=request.token,
            accepted=accepted,
            evaluation_id=evaluation_id,
            detail=detail,
        )

    async def _forward(self, robot: str) -> tuple[bool, int | None, str]:
        members = list(self._members())
        if robot not in members:
            known = ", ".join(members) if members else "none yet"
            return False, None, f"{robot} is not in this run (its robots: {known})"
        paused = self._paused()
        if paused is not None:
            return False, None, f"the run is paused ({paused}): its robots stand still"
        deadline = asyncio.get_running_loop().time() + EVALUATION_WAIT
        while True:
            session = self.server.sessions.get(robot)
            if session is None:
                return False, None, f"{robot} is not connected"
            if FEATURE_ESCAPE not in session.hello.features:
                version = printable(session.hello.software_version)
                return (
                    False,
                    None,
                    (
                        f"{robot}'s agent (software {version}) does not know the experimenter's "
                        "escape: update it"
                    ),
                )
            if self._evaluating(robot):
                reply = await self._ask(session)
                if reply is None:
                    return False, None, f"{robot} did not answer within {REPLY_TIMEOUT:g} s"
                if reply.accepted:
                    return True, reply.evaluation_id, ""
                # Between the check and the answer its evaluation may have ended: try again
                # while there is time; any other refusal is the robot's last word.
                if not reply.reason.startswith(f"{ESCAPE_REFUSED_IDLE}:"):
                    return False, None, f"{robot} refused: {printable(reply.reason)}"
            if asyncio.get_running_loop().time() >= deadline:
                return (
                    False,
                    None,
                    (
                        f"no evaluation ran on {robot} within {EVALUATION_WAIT:g} s (the run waits "
                        "for robots, or is ending): it stands still"
                    ),
                )
            await asyncio.sleep(0.05)

    async def _ask(self, session: Session) -> EscapeReply | None:
        self._seq += 1
        key = (session.robot_id, self._seq)
        future: asyncio.Future[EscapeReply] = asyncio.get_running_loop().create_future()
        self._waiting[key] = future
        try:
            if self.server.send([session.robot_id], encode_payload(Escape(seq=self._seq))):
                return None  # not reached: the session ended under us
            try:
                async with asyncio.timeout(REPLY_TIMEOUT):
                    return await future
            except TimeoutError:
                return None
        finally:
            del self._waiting[key]
