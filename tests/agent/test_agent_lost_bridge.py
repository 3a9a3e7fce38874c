"""An agent whose I2C bridge dies mid-evaluation (surprise-sim-robots killed, docs/rehearsal.md):
its force reads fail like a failed chip's, the control loop stops the robot for each lost step,
and after ``max_read_failures`` in a row the evaluation fails with the reason and the motors
stopped, as for any hardware fault."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from pathlib import Path

from agent_fakes import genome, spec

from drivers.clock import MonotonicClock
from drivers.compose import build_body
from drivers.config import BodyConfig, ThymioConfig
from minimize_surprise.sensors import FORCE_SENSORS, GROUND_SENSORS, IR_SENSORS
from minimize_surprise.wire import Evaluate, Failed, genome_to_bytes
from robot_agent.config import LoopConfig
from robot_agent.runner import EvaluationRunner
from standins.fake_medulla import StaticThymioModel, serve_fake_medulla
from standins.i2c_bridge import SERVED_FORCE, RobotChips, serve_i2c_bridge

#: Steps of 0.1 s (the loop's shortest period), far more than the test lasts: the evaluation
#: ends by the failure.
STEPS = 200
#: Seconds for anything the test waits for (the robot to drive, the evaluation to fail).
WAIT = 5.0


async def test_an_agent_whose_bridge_dies_fails_the_evaluation_and_stops(
    tmp_path: Path, dbus_address: str
):
    bridge = tmp_path / "robot.sock"
    chips = RobotChips(SERVED_FORCE, (), lambda: 0.0, lambda _: 0.0)
    model = StaticThymioModel(prox=[0] * 7, reflected=[400, 400])
    config = BodyConfig(
        thymio=ThymioConfig(bus=dbus_address), force=SERVED_FORCE, i2c_bridge=str(bridge)
    )
    network = spec(IR_SENSORS + GROUND_SENSORS + FORCE_SENSORS)
    evaluate = Evaluate(
        evaluation_id=1,
        genome=genome_to_bytes(genome(network, speed_bias=2.0)),
        spec=network,
        steps=STEPS,
        step_period=0.1,
    )
    async with serve_fake_medulla(dbus_address, model), contextlib.AsyncExitStack() as server:
        await server.enter_async_context(serve_i2c_bridge(bridge, chips.i2c))
        body = build_body(config)
        async with body:
            runner = EvaluationRunner(body, MonotonicClock(), loop=LoopConfig())
            task = asyncio.create_task(runner.run(evaluate))
            await _until(lambda: model.targets["left"] > 0)  # driving
            await server.aclose()  # the bridge's server dies mid-evaluation
            outcome = await asyncio.wait_for(task, WAIT)
    assert isinstance(outcome, Failed), outcome
    assert outcome.reason.startswith("sensor-read: 3 reads in a row failed"), outcome.reason
    assert f"I2C bridge {bridge}" in outcome.reason
    # The lost steps stopped the robot, and so did the end of the evaluation.
    assert model.target_log[-2:] == [("left", 0), ("right", 0)]
    assert model.targets == {"left": 0, "right": 0}


async def _until(condition: Callable[[], bool]) -> None:
    deadline = time.monotonic() + WAIT
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        await asyncio.sleep(0.01)
