"""A robot that cannot be reached: the evaluation that finds out fails with ``robot-unreachable``,
later ones fail at once without driving, and the background recovery brings it back."""

from __future__ import annotations

import asyncio
import logging
import random

import pytest
from agent_fakes import FakeBody, FakeClock, genome, spec

from minimize_surprise.backoff import BackoffConfig
from minimize_surprise.errors import HardwareError, RobotUnreachableError
from minimize_surprise.wire import Evaluate, Failed, Result, genome_to_bytes
from robot_agent.config import LoopConfig
from robot_agent.health import FAILED_UNREACHABLE, RobotHealth
from robot_agent.runner import EvaluationRunner

QUICK = BackoffConfig(initial=0.01, max=0.02, jitter=0.0)


class LosingBody(FakeBody):
    """Reads raise RobotUnreachableError from read ``lose_at`` on; stops fail while ``gone``;
    ``recover()`` succeeds once ``back`` is set."""

    def __init__(self, *, lose_at: int = 10**9, stop_gone: bool = False, **kwargs) -> None:
        super().__init__(**kwargs)
        self.lose_at = lose_at
        self.stop_gone = stop_gone
        self.back = asyncio.Event()
        self.recover_calls = 0

    async def read(self):
        if self.reads >= self.lose_at and not self.back.is_set():
            self.reads += 1
            raise RobotUnreachableError("asebamedulla :1.4 has ended")
        return await super().read()

    async def stop(self) -> None:
        await super().stop()
        if self.stop_gone and not self.back.is_set():
            raise RobotUnreachableError("stop not confirmed: the robot does not answer")

    async def recover(self) -> None:
        self.recover_calls += 1
        if not self.back.is_set():
            raise HardwareError("no node yet")


def evaluate(eid: int, steps: int = 10) -> Evaluate:
    network = spec()
    return Evaluate(
        evaluation_id=eid,
        genome=genome_to_bytes(genome(network, speed_bias=2.0)),
        spec=network,
        steps=steps,
        step_period=0.1,
    )


def runner_for(body: FakeBody, clock: FakeClock) -> tuple[EvaluationRunner, RobotHealth]:
    health = RobotHealth(body, rng=random.Random(1), backoff=QUICK)
    runner = EvaluationRunner(body, clock, loop=LoopConfig(), health=health)
    return runner, health


async def test_a_lost_robot_ends_the_evaluation_at_once_and_later_ones_fail_without_driving():
    clock = FakeClock()
    body = LosingBody(lose_at=3, clock=clock)
    runner, health = runner_for(body, clock)
    failed = await runner.run(evaluate(1))
    assert isinstance(failed, Failed)
    assert failed.reason.startswith(f"{FAILED_UNREACHABLE}: ") and ":1.4 has ended" in failed.reason
    assert body.reads == 4  # the first unreachable read ends it; no counting to the limit
    assert body.motors == (0.0, 0.0) and not health.reachable
    drives, reads = len(body.drives), body.reads
    again = await runner.run(evaluate(2))
    assert isinstance(again, Failed) and again.reason.startswith(f"{FAILED_UNREACHABLE}: for ")
    assert (len(body.drives), body.reads) == (drives, reads)


async def test_a_stop_the_robot_does_not_confirm_makes_the_evaluation_fail():
    # Every step ran, but the robot did not confirm the final stop: it may still be driving, and
    # the master must not count a result from a robot it cannot reach.
    clock = FakeClock()
    body = LosingBody(stop_gone=True, clock=clock)
    runner, health = runner_for(body, clock)
    failed = await runner.run(evaluate(1))
    assert isinstance(failed, Failed) and "stop not confirmed" in failed.reason
    assert failed.reason.startswith(FAILED_UNREACHABLE) and not health.reachable


async def test_recovery_retries_until_the_robot_is_back_and_says_so(caplog):
    caplog.set_level(logging.DEBUG, logger="robot_agent.health")
    clock = FakeClock()
    body = LosingBody(lose_at=0, clock=clock)
    runner, health = runner_for(body, clock)
    task = asyncio.create_task(health.run())
    try:
        assert isinstance(await runner.run(evaluate(1)), Failed)
        while body.recover_calls < 3:
            await asyncio.sleep(0.005)
        assert not health.reachable
        body.back.set()
        await asyncio.wait_for(health.wait_reachable(), 1.0)
        assert health.reachable and health.losses == 1 and health.recoveries == 1
        assert isinstance(await runner.run(evaluate(2)), Result)
    finally:
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
    messages = [r.getMessage() for r in caplog.records]
    assert sum("robot unreachable:" in m for m in messages) == 1  # said once, not per attempt
    assert any("robot reachable again after" in m for m in messages)
    assert sum(r.levelno >= logging.INFO and "still unreachable" in r.getMessage()
               for r in caplog.records) == 1  # fmt: skip


async def test_losing_twice_is_reported_once_until_recovered():
    body = LosingBody()
    health = RobotHealth(body, backoff=QUICK)
    health.lost("first reason")
    health.lost("second reason")
    assert health.losses == 1 and "first reason" in health.failure()


async def test_while_recovery_fails_evaluations_say_why_the_robot_is_still_unreachable():
    # A wrong bus, medulla not running: the master's log must show the cause, not only that the
    # robot was lost once.
    clock = FakeClock()
    body = LosingBody(lose_at=0, clock=clock)
    runner, health = runner_for(body, clock)
    task = asyncio.create_task(health.run())
    try:
        first = await runner.run(evaluate(1))
        assert isinstance(first, Failed) and "has ended" in first.reason
        while body.recover_calls < 2:
            await asyncio.sleep(0.005)
        later = await runner.run(evaluate(2))
        assert isinstance(later, Failed) and later.reason.startswith(FAILED_UNREACHABLE)
        assert later.reason.endswith(": no node yet")
    finally:
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
