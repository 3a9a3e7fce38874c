"""The agent compiles its control step when it starts, not at the first step of the first
evaluation: on a fresh Pi that compile took seconds, and a swarm's first round missed its
deadline. Checked in a fresh interpreter, whose kernels have no compiled code yet, by asking
numba which signatures each kernel holds once the agent has started and before any evaluation."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from needs import require_module

HERE = Path(__file__).resolve().parent

_SCRIPT = """
import asyncio, json, random, sys
sys.path.insert(0, {here!r})
from agent_fakes import SECRET, agent_config
import simulator.body as sim_body, simulator.scenarios as scenarios, simulator.world as world_module
from minimize_surprise.fitness import step_score
from minimize_surprise.network import network_step
from minimize_surprise.safety import safety_step
from robot_agent.agent import Agent

kernels = {{"network_step": network_step, "step_score": step_score, "safety_step": safety_step}}

async def main():
    before = {{name: len(k.signatures) for name, k in kernels.items()}}
    world = world_module.World(scenarios.scenario_config("basic", {{"robots": 1}}), 0)
    body = sim_body.SimSwarm(world).bodies()[0]
    async with body:
        # No master listens on port 9: the agent starts and keeps trying to connect.
        agent = Agent(agent_config(9), body, body.clock, SECRET, rng=random.Random(0))
        async with agent:
            after = {{name: len(k.signatures) for name, k in kernels.items()}}
    print(json.dumps({{"before": before, "after": after}}))

asyncio.run(main())
"""


def test_the_control_step_is_compiled_before_the_agent_joins() -> None:
    require_module("numba", "master")
    result = subprocess.run(
        [sys.executable, "-c", _SCRIPT.format(here=str(HERE))],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    seen = json.loads(result.stdout.strip().splitlines()[-1])
    assert seen["before"] == {"network_step": 0, "step_score": 0, "safety_step": 0}
    assert all(count >= 1 for count in seen["after"].values()), seen
