"""The agent's telemetry against a real broker: the documented topics and payloads of an
evaluation, online and offline, and a control loop that neither a full queue nor a broker going
away and coming back can slow down or change."""

from __future__ import annotations

import asyncio
import contextlib
import math
import random
from collections.abc import AsyncIterator

import numpy as np
import pytest
from agent_fakes import (
    SECRET,
    THYMIO,
    FakeBody,
    FakeClock,
    ScriptedMaster,
    agent_config,
    genome,
    receive,
    spec,
)
from telemetry_helpers import eventually

from minimize_surprise.backoff import BackoffConfig
from minimize_surprise.wire import Evaluate, Failed, Result, genome_to_bytes
from robot_agent.agent import Agent
from robot_agent.runner import EvaluationRunner
from telemetry.config import TelemetryConfig
from telemetry.publisher import TelemetryPublisher
from telemetry.robot import RobotTelemetry

FAST = BackoffConfig(initial=0.02, max=0.1, jitter=0.5)


def frames(i: int) -> np.ndarray:
    """Clear sensors, except an obstacle ahead at reads 6 and 7 (the safety layer stops)."""
    frame = np.full(len(THYMIO), 0.1)
    if i in (6, 7):
        frame[THYMIO.index("ir.f2")] = 0.9
    return frame


def evaluate(eid: int, steps: int) -> Evaluate:
    network = spec()
    return Evaluate(
        evaluation_id=eid,
        genome=genome_to_bytes(genome(network, speed_bias=2.0)),
        spec=network,
        steps=steps,
        step_period=0.1,
        record=False,
    )


@contextlib.asynccontextmanager
async def running(agent: Agent) -> AsyncIterator[None]:
    task = asyncio.create_task(agent.run())
    try:
        yield
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


async def test_an_agent_publishes_status_evaluations_and_samples(mosquitto, subscriber):
    master = ScriptedMaster()
    await master.start()
    clock = FakeClock()
    body = FakeBody(frames, clock=clock)
    telemetry = TelemetryConfig(broker=mosquitto.url, rate_hz=2, reconnect=FAST)
    agent = Agent(
        agent_config(master.port, telemetry=telemetry), body, clock, SECRET, rng=random.Random(1)
    )
    try:
        async with subscriber(mosquitto.port) as live:
            async with running(agent):
                assert (await live.wait_for("robot/r1/status"))["online"] is True
                stream = await master.next()
                await master.welcome(stream)
                await stream.send(evaluate(7, 20))
                result = await receive(stream)
                assert isinstance(result, Result)
                summary = await live.wait_for("robot/r1/evaluation")
                await eventually(lambda: len(live.payloads("robot/r1/sample")) == 4)
            offline = await live.wait_for("robot/r1/status", lambda p: not p["online"])
    finally:
        await master.close()

    assert set(summary) == {
        "v", "t", "evaluation", "requested", "steps", "fitness", "failure", "interventions",
        "overruns", "read_failures", "duration_s", "battery_v",
    }  # fmt: skip
    assert summary["v"] == 1 and summary["evaluation"] == 7
    assert (summary["requested"], summary["steps"]) == (20, 20)
    assert summary["fitness"] == result.fitness and summary["failure"] is None
    assert summary["interventions"] == result.stats.interventions == {"front": 2}
    assert summary["overruns"] == 0 and summary["read_failures"] == 0
    assert summary["duration_s"] == pytest.approx(2.0)  # 20 steps of 0.1 s on the robot's clock

    samples = live.payloads("robot/r1/sample")
    # 2 Hz at 10 Hz: every fifth step.
    assert [s["step"] for s in samples] == [5, 10, 15, 20]
    for s in samples:
        assert set(s) == {
            "v", "t", "evaluation", "step", "names", "sensors", "predictions", "command", "reason",
        }  # fmt: skip
        assert s["v"] == 1 and s["evaluation"] == 7 and s["names"] == list(THYMIO)
        assert s["sensors"] == [0.1] * len(THYMIO)
        assert s["predictions"] == [0.5] * len(THYMIO)  # zero weights: sigmoid(0)
        # The command applied at that step: the motor write of step k is drive k - 1.
        assert s["command"] == pytest.approx(body.drives[s["step"] - 1], abs=1e-4)
    ahead = round(math.tanh(2.0), 4)
    assert samples[0]["command"] == [ahead, ahead]
    assert samples[0]["reason"] is None
    assert offline["online"] is False and offline["dropped"] == 0


async def test_a_refused_evaluation_is_summarised_as_failed(mosquitto, subscriber):
    clock = FakeClock()
    body = FakeBody(0.1, clock=clock)
    async with subscriber(mosquitto.port) as live:
        pub = TelemetryPublisher(
            TelemetryConfig(broker=mosquitto.url, reconnect=FAST), status_suffix="robot/r1/status"
        )
        async with pub:
            runner = EvaluationRunner(body, clock, telemetry=RobotTelemetry(pub, "r1"))
            network = spec((*THYMIO, "light.0"))
            msg = Evaluate(
                evaluation_id=3,
                genome=genome_to_bytes(genome(network)),
                spec=network,
                steps=10,
                step_period=0.1,
                record=False,
            )
            assert isinstance(await runner.run(msg), Failed)
            summary = await live.wait_for("robot/r1/evaluation")
    assert summary["fitness"] is None and summary["steps"] == 0
    assert summary["failure"].startswith("missing-sensors: ")
    assert live.payloads("robot/r1/sample") == []


async def _run(runner: EvaluationRunner, steps: int) -> Result:
    outcome = await runner.run(evaluate(1, steps))
    assert isinstance(outcome, Result)
    return outcome


@pytest.mark.parametrize("started", [False, True], ids=["never-started", "broker-unreachable"])
async def test_a_full_queue_drops_the_oldest_without_touching_the_loop(started, closed_port):
    steps = 200
    # The reference: the same evaluation without telemetry.
    clock = FakeClock()
    reference_body = FakeBody(frames, clock=clock)
    reference = await _run(EvaluationRunner(reference_body, clock), steps)

    clock = FakeClock()
    body = FakeBody(frames, clock=clock)
    config = TelemetryConfig(
        broker=f"mqtt://127.0.0.1:{closed_port}", rate_hz=10, queue_size=2, reconnect=FAST
    )
    pub = TelemetryPublisher(config, status_suffix="robot/r1/status")
    runner = EvaluationRunner(body, clock, telemetry=RobotTelemetry(pub, "r1"))
    if started:
        pub.start()
    try:
        outcome = await _run(runner, steps)
    finally:
        await pub.aclose()
    # Identical behaviour, step for step and deadline for deadline.
    assert outcome.fitness == reference.fitness and outcome.stats == reference.stats
    assert body.drives == reference_body.drives
    assert clock.deadlines == reference_body.clock.deadlines  # same start, same grid
    assert outcome.stats.overruns == 0
    # 200 samples (10 Hz: every step) and one summary went into a queue of 2.
    assert pub.dropped == steps + 1 - 2 and pub.sent == 0
    assert [type(p).__name__ for _, p, _ in pub._queue] == ["StepSample", "EvaluationSummary"]


async def test_the_broker_stopped_and_restarted_mid_evaluation(mosquitto, subscriber):
    steps = 300

    def values(i: int) -> np.ndarray:
        # The broker goes away a quarter into the evaluation and comes back at the middle.
        if i == 75:
            mosquitto.stop()
        elif i == 150:
            mosquitto.start()
        return frames(i)

    clock = FakeClock()
    reference_body = FakeBody(frames, clock=clock)
    reference = await _run(EvaluationRunner(reference_body, clock), steps)

    clock = FakeClock()
    body = FakeBody(values, clock=clock)
    config = TelemetryConfig(broker=mosquitto.url, rate_hz=10, queue_size=1000, reconnect=FAST)
    async with TelemetryPublisher(config, status_suffix="robot/r1/status") as pub:
        runner = EvaluationRunner(body, clock, telemetry=RobotTelemetry(pub, "r1"))
        await eventually(lambda: pub.connected)
        outcome = await _run(runner, steps)
        assert outcome.fitness == reference.fitness and outcome.stats == reference.stats
        assert body.drives == reference_body.drives
        # The publisher reconnected by itself and what was queued meanwhile went out.
        await eventually(lambda: pub.connections == 2 and pub.pending == 0)
        assert pub.dropped == 0
        # Later messages arrive.
        async with subscriber(mosquitto.port) as live:
            assert (await live.wait_for("robot/r1/status"))["online"] is True
            later = await _run(runner, 10)
            summary = await live.wait_for("robot/r1/evaluation")
            assert summary["fitness"] == later.fitness
            await eventually(lambda: len(live.payloads("robot/r1/sample")) == 10)
