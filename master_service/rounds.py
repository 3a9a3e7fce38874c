"""One evaluation attempt: send a genome to the swarm, collect one result per robot or give up.

An attempt succeeds when every robot of the swarm answered with a Result before the deadline
(``steps * step_period + margin``, with the experiment's period that the Evaluate carries). It
fails on the first Failed, when a robot that has not answered yet leaves, or at the deadline; a
failed attempt is aborted on every robot. Results of other evaluation ids (late answers to aborted
attempts) and second answers are ignored: the evaluation id is unique per attempt, so nothing can
be counted twice.

The evolution loop that asks and tells lives in :mod:`master_service.master`.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from collections.abc import Callable, Sequence
from typing import Final

import numpy as np

from master_service.server import RobotServer, Session
from minimize_surprise.network import NetworkSpec
from minimize_surprise.safety import intervention_share
from minimize_surprise.wire import (
    Abort,
    Evaluate,
    Failed,
    Result,
    encode_payload,
    genome_to_bytes,
    printable,
)

__all__ = ["Attempt", "RoundRunner"]

#: How many per-round overheads to keep for benchmarks and diagnostics.
OVERHEAD_HISTORY: Final = 10_000


class Attempt:
    """One attempt at evaluating a genome on ``robots``; ``results`` fills as answers arrive.

    ``failure`` is None while running and after success; otherwise why the attempt failed.
    ``started`` and ``completed`` are ``time.perf_counter()`` values (the Evaluate written to
    every robot; the last Result in); ``sent_at`` is the wall-clock time of the first.
    """

    def __init__(self, evaluation_id: int, robots: Sequence[str], record: bool) -> None:
        self.evaluation_id = evaluation_id
        self.robots = tuple(robots)
        # For membership tests per answer: with a thousand robots a tuple scan would make a round
        # quadratic.
        self.members = frozenset(self.robots)
        self.record = record
        self.results: dict[str, Result] = {}
        self.failure: str | None = None
        self.finished = asyncio.Event()
        self.started = 0.0
        self.completed = 0.0
        self.sent_at: float | None = None

    @property
    def ok(self) -> bool:
        """True when every robot answered."""
        return self.finished.is_set() and self.failure is None

    @property
    def missing(self) -> list[str]:
        """The robots that have not answered (yet)."""
        return [r for r in self.robots if r not in self.results]

    def fail(self, reason: str) -> None:
        """End the attempt as failed (the first reason wins)."""
        if not self.finished.is_set():
            self.failure = reason
            self.finished.set()

    def fitnesses(self) -> list[float]:
        """The robots' fitnesses in the order of ``robots`` (a fixed order: a float mean then
        comes out the same bit for bit however the answers interleaved)."""
        return [self.results[r].fitness for r in self.robots]

    def safety_share(self) -> float:
        """The share of the robots' steps in which the safety layer changed the command."""
        stats = [self.results[r].stats for r in self.robots]
        return intervention_share((s.interventions for s in stats), sum(s.steps_run for s in stats))


class RoundRunner:
    """Runs attempts over a :class:`RobotServer` and routes the robots' answers to them.

    ``overheads`` holds, for each attempt that directly followed a successful one, the seconds
    from the previous attempt's last Result to this attempt's Evaluate written to every robot.
    """

    def __init__(self, server: RobotServer, margin: float, logger: logging.Logger) -> None:
        self.server = server
        self.margin = margin
        self.log = logger
        self.current: Attempt | None = None
        self.overheads: collections.deque[float] = collections.deque(maxlen=OVERHEAD_HISTORY)
        self._previous_completed: float | None = None

    def deadline(self, steps: int, step_period: float) -> float:
        """Seconds an attempt of ``steps`` control steps of ``step_period`` seconds may take (a
        simulated swarm in lockstep is faster; the deadline is only an upper bound)."""
        return steps * step_period + self.margin

    # -- callbacks from the server -----------------------------------------------------------

    def on_message(self, session: Session, msg: Result | Failed) -> None:
        """Route a Result or Failed to the running attempt; ignore anything late or repeated."""
        attempt = self.current
        robot_id = session.robot_id
        if attempt is None or msg.evaluation_id != attempt.evaluation_id:
            self.log.info(
                "ignored a late %s for evaluation %d from robot %s",
                type(msg).__name__,
                msg.evaluation_id,
                robot_id,
            )
            return
        if attempt.finished.is_set() or robot_id not in attempt.members:
            self.log.info(
                "ignored a %s for evaluation %d from robot %s: the attempt is over",
                type(msg).__name__,
                msg.evaluation_id,
                robot_id,
            )
            return
        if robot_id in attempt.results:
            self.log.info(
                "ignored a duplicate answer for evaluation %d from robot %s",
                msg.evaluation_id,
                robot_id,
            )
            return
        if isinstance(msg, Failed):
            attempt.fail(f"robot {robot_id} could not evaluate: {printable(msg.reason)}")
            return
        if attempt.record and msg.trace is None:
            self.log.warning("robot %s sent its post-evaluation without a trace", robot_id)
        attempt.results[robot_id] = msg
        if len(attempt.results) == len(attempt.robots):
            attempt.completed = time.perf_counter()
            attempt.finished.set()

    def on_leave(self, session: Session, reason: str) -> None:
        """A robot left: the running attempt fails if that robot still owed its answer."""
        attempt = self.current
        robot_id = session.robot_id
        if attempt is not None and robot_id in attempt.members and robot_id not in attempt.results:
            attempt.fail(f"robot {robot_id} left: {reason}")

    # -- attempts ----------------------------------------------------------------------------

    async def run(
        self,
        *,
        evaluation_id: int,
        genome: np.ndarray,
        spec: NetworkSpec,
        steps: int,
        step_period: float,
        record: bool,
        robots: Sequence[str],
        post_evaluation: bool = False,
        on_sent: Callable[[int, float], None] | None = None,
    ) -> Attempt:
        """Send one Evaluate to ``robots`` and wait for the outcome; abort everywhere on failure.

        ``post_evaluation`` marks it so (the robots flash); ``on_sent(evaluation_id, sent_at)``
        is told the wall-clock time it went out.
        """
        attempt = Attempt(evaluation_id, robots, record)
        message = Evaluate(
            evaluation_id=evaluation_id,
            genome=genome_to_bytes(genome),
            spec=spec,
            steps=steps,
            step_period=step_period,
            record=record,
            post_evaluation=post_evaluation,
        )
        # One encoding for the whole swarm: every robot gets the same bytes, tagged per session.
        payload = encode_payload(message)
        self.current = attempt
        try:
            missed = self.server.send(robots, payload)
            attempt.started = time.perf_counter()
            attempt.sent_at = time.time()
            if on_sent is not None:
                on_sent(evaluation_id, attempt.sent_at)
            if self._previous_completed is not None:
                self.overheads.append(attempt.started - self._previous_completed)
            self._previous_completed = None
            if missed:
                attempt.fail(f"robots {', '.join(missed)} could not be sent the genome")
            deadline = self.deadline(steps, step_period)
            try:
                async with asyncio.timeout(deadline):
                    await attempt.finished.wait()
            except TimeoutError:
                attempt.fail(
                    f"no result within {deadline:.1f} s from robots {', '.join(attempt.missing)}"
                )
        finally:
            self.current = None
        if attempt.ok:
            self._previous_completed = attempt.completed
        else:
            abort = Abort(evaluation_id=evaluation_id, reason=attempt.failure or "cancelled")
            live = [r for r in robots if r in self.server.sessions]
            self.server.send(live, encode_payload(abort))
        return attempt
