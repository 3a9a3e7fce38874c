"""The experimenter's hand and the start flash on a Playground Thymio behind Debian's own
``asebamedulla``: a ``surprise-agent`` process in the escape profile takes an Escape in the middle
of a post-evaluation, its safety layer reverses the robot at full speed (as medulla's motor
targets show), and the Result counts it; the start flash fails on Playground's Thymio, which has
no ``leds.top`` variable, with one line in the agent's log, and the evaluation runs to its end."""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest
import yaml
from aseba_stack import Observer
from test_real_aseba import AGENT_TIMEOUT, SECRET, lab_of, straight, until

from minimize_surprise.safety import REASON_ESCAPE, REASON_EXPERIMENTER
from minimize_surprise.wire import FEATURE_ESCAPE, Escape, EscapeReply, Result

pytestmark = pytest.mark.slow

#: 8 s at 10 Hz: the escape's reverse (3 s) and part of its turn fit after the robot set off.
STEPS = 80
#: The reverse's motor target: full speed at the default speed scale (265 units).
REVERSE = -265


async def test_an_escape_and_the_start_flash_on_a_playground_robot(tmp_path: Path):
    from agent_fakes import ScriptedMaster

    master = ScriptedMaster()
    await master.start()
    try:
        async with lab_of(tmp_path, 1) as lab, Observer(lab.robots[0].address) as robot:
            config = lab.agent_config(0, master.port)
            data = yaml.safe_load(config.read_text())
            # The escape profile, with no rule of its own firing on Playground's white floor:
            # whatever the robot does besides driving straight is the experimenter's escape.
            data["safety"] = {
                "profile": "escape",
                "ground_threshold": 1.0,
                "escape_front_threshold": 1.0,
                "escape_rear_threshold": 1.0,
            }
            config.write_text(yaml.safe_dump(data))
            lab.start_agent(0, config)
            stream = await master.next(AGENT_TIMEOUT)
            hello = await master.welcome(stream, SECRET)
            assert FEATURE_ESCAPE in hello.features
            evaluate = straight(1, steps=STEPS)
            await stream.send(msgspec.structs.replace(evaluate, record=True, post_evaluation=True))

            async def driving() -> bool:
                left, right = await robot.targets()
                return left > 0 and right > 0

            async def reversing() -> bool:
                return await robot.targets() == (REVERSE, REVERSE)

            await until(driving, AGENT_TIMEOUT, "the robot to drive", lab)
            await stream.send(Escape(seq=1))
            reply = await stream.receive()
            assert isinstance(reply, EscapeReply) and reply.seq == 1, reply
            assert reply.accepted and reply.evaluation_id == 1, reply
            await until(reversing, 2.0, "the safety layer to reverse the robot", lab)

            result = await stream.receive()
            while not isinstance(result, Result):  # a ping of the agent's, if it came
                result = await stream.receive()
            assert result.evaluation_id == 1 and result.stats.steps_run == STEPS
            counts = result.stats.interventions
            assert counts[REASON_EXPERIMENTER] == 1 and counts[REASON_ESCAPE] >= 29, counts
            assert result.trace is not None
            assert result.trace.safety.count(REASON_EXPERIMENTER) == 1
            assert await robot.targets() == (0, 0)
            log = lab.output("agent-0")
            assert "the experimenter's escape started at step" in log
            # Playground's Thymio has no leds.top: said once, and nothing else minded it.
            flash = [line for line in log.splitlines() if "start flash failed" in line]
            assert len(flash) == 1 and "has no leds.top variable" in flash[0], log
    finally:
        await master.close()
