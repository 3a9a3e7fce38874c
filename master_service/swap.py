"""Lose one, go on: ``surprise-master swap RUN_DIR GONE SPARE`` (docs/runs.md).

A robot of the swarm away for longer than the master's ``robot_gone_after`` (a dead battery, a
crashed Pi) pauses the run naming it (:class:`~master_service.pause.Pause` of kind
``robot-gone``). A spare then takes its place: the command drops a
:class:`~runfiles.schema.SwapRequest` into the run directory's ``requests/``
(:func:`request_swap`), as the experimenter's escape does (:mod:`master_service.escape`); the
master's :class:`SwapDesk` takes it within :data:`POLL_INTERVAL`, checks it, waits up to
:data:`SPARE_WAIT` for the spare's agent to be connected, has the evolution loop change the swarm
(``apply``) and appends an :class:`~runfiles.schema.Event` of kind ``swarm-change`` with the
outcome to ``events.jsonl``, which the command waits for and prints.

Refused, each with one line and the swarm untouched: an id no robot can have; GONE not in the
swarm; GONE connected (a swap replaces a robot that is gone: stop its agent first); SPARE in the
swarm already; SPARE not among the master file's ``allowed_robots`` (when it lists any); SPARE
not connected within :data:`SPARE_WAIT`; the run done. A request the master cannot read is
logged and dropped; it never reaches the run's state.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Sequence
from typing import Final

from master_service import desk
from master_service.desk import new_token
from master_service.rundir import RunDir, RunDirError, RunState
from master_service.server import RobotServer
from minimize_surprise.wire import is_valid_robot_id
from runfiles.schema import (
    EVENT_SWARM_CHANGE,
    Event,
    SwapRequest,
)

__all__ = [
    "ANSWER_TIMEOUT",
    "POLL_INTERVAL",
    "SPARE_WAIT",
    "SwapDesk",
    "request_swap",
    "swap_request",
]

#: Seconds between two looks into ``requests/``: far below a person's reaction, one ``scandir``.
POLL_INTERVAL: Final = 0.25
#: Seconds the master waits for the spare's agent to be connected: an agent refused or away
#: tries again after at most its backoff's 30 s (``minimize_surprise.backoff``), and a spare
#: switched on with the command needs its handshake too.
SPARE_WAIT: Final = 45.0
#: Seconds the command waits for the master's answer: its poll and the wait for the spare, with
#: room for a busy laptop and the commit that makes the new swarm durable.
ANSWER_TIMEOUT: Final = POLL_INTERVAL + SPARE_WAIT + 10.0
#: Seconds between two looks of the desk for the spare's connection.
_SPARE_POLL: Final = 0.05


def swap_request(gone: str, spare: str) -> SwapRequest:
    """A request that ``spare`` take ``gone``'s place. Raises :class:`RunDirError` for an id no
    robot can have, or a robot named for its own place."""
    for robot in (gone, spare):
        if not is_valid_robot_id(robot):
            raise RunDirError(f"{robot!r} is not a robot id (letters, digits, '.', '_', '-')")
    if gone == spare:
        raise RunDirError(f"{gone} cannot take its own place: name a spare")
    return SwapRequest(gone=gone, spare=spare, token=new_token(), requested_at=time.time())


def request_swap(
    run_dir: RunDir, gone: str, spare: str, *, timeout: float = ANSWER_TIMEOUT
) -> Event:
    """Ask the master running ``run_dir`` to put ``spare`` in ``gone``'s place; its answer (a
    ``swarm-change`` event: ``accepted`` with the evaluation the new swarm starts at, or why
    not in ``detail``).

    Raises :class:`RunDirError` when no master runs the run (``master_alive``), for an id no
    robot can have, or when the master does not answer within ``timeout`` (the request is then
    taken back when it was not taken yet, so that it never acts late).
    """
    request = swap_request(gone, spare)
    path = run_dir.path
    not_running = (
        f"no master is running {path}: a swap changes a running run's swarm; resume it "
        f"with `surprise-master resume {path}` first"
    )
    return desk.ask_master(
        path, request, EVENT_SWARM_CHANGE, timeout=timeout, not_running=not_running
    )


class SwapDesk:
    """The master's side: takes the swap requests in ``run_dir``'s ``requests/`` and answers
    each with a ``swarm-change`` event (see the module docstring); :meth:`run` until cancelled.

    ``state()`` is the run's (None before it is loaded; a swap changes a fixed swarm only);
    ``allowed`` the master file's ``allowed_robots`` (empty: any robot with the secret);
    ``apply(gone, spare)`` changes the swarm between evaluations and returns the counted
    evaluation the new swarm starts at. While a spare is waited for, :attr:`expecting` names it,
    and the master admits it though it is not in the swarm.
    """

    def __init__(
        self,
        run_dir: RunDir,
        server: RobotServer,
        log: logging.Logger,
        state: Callable[[], RunState | None],
        allowed: Sequence[str],
        apply: Callable[[str, str], int],
    ) -> None:
        self.run_dir = run_dir
        self.server = server
        self.log = log
        self._state = state
        self._allowed = list(allowed)
        self._apply = apply
        #: spares a swap waits for: admitted while they are
        self.expecting: set[str] = set()

    async def run(self) -> None:
        """Answer requests until cancelled, one after the other in the order they came."""
        await desk.serve_requests(
            self.run_dir.path, SwapRequest, self.handle, self.log, "the swap",
            lambda: POLL_INTERVAL,
        )  # fmt: skip

    async def handle(self, request: SwapRequest) -> Event:
        """Check ``request``, wait for its spare, change the swarm; the event that says how."""
        gone, spare = request.gone, request.spare
        refusal = self._check(gone, spare)
        from_evaluation = None
        if refusal is None:
            refusal = await self._wait_for(spare)
        if refusal is None:
            # The wait gave the gone robot time to come back, or another swap to take its place.
            refusal = self._check(gone, spare)
        if refusal is None:
            from_evaluation = self._apply(gone, spare)
            self.log.warning(
                "swap: %s takes the place of %s from evaluation %d on", spare, gone, from_evaluation
            )
        else:
            self.log.warning("swap of %s for %s refused: %s", gone, spare, refusal)
        return Event(
            time=time.time(),
            kind=EVENT_SWARM_CHANGE,
            robot=gone,
            joined=spare,
            request=request.token,
            accepted=refusal is None,
            evaluation_id=from_evaluation,
            detail=refusal or "",
        )

    def _check(self, gone: str, spare: str) -> str | None:
        if not (is_valid_robot_id(gone) and is_valid_robot_id(spare)) or gone == spare:
            return "the request names no robot and spare"
        state = self._state()
        if state is not None and state.phase == "done":
            return "the run is done: its swarm no longer changes"
        members = [] if state is None or state.roster is None else list(state.roster)
        if gone not in members:
            known = ", ".join(members) if members else "none yet"
            return f"{gone} is not in this run's swarm (its robots: {known})"
        if spare in members:
            return f"{spare} is in the swarm already"
        if self._allowed and spare not in self._allowed:
            return (
                f"{spare} is unknown: not among the master file's allowed_robots "
                f"({', '.join(self._allowed)})"
            )
        if gone in self.server.sessions:
            return f"{gone} is connected: a swap replaces a robot that is gone (stop its agent)"
        return None

    async def _wait_for(self, spare: str) -> str | None:
        self.expecting.add(spare)
        try:
            deadline = time.monotonic() + SPARE_WAIT
            while spare not in self.server.sessions:
                if time.monotonic() >= deadline:
                    return f"{spare} did not connect within {SPARE_WAIT:g} s"
                await asyncio.sleep(_SPARE_POLL)
        finally:
            self.expecting.discard(spare)
        return None
