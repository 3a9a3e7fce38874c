"""Several agents with simulated bodies in one event loop, the way the master's ``sim`` command
runs them: lockstep world, loopback TCP, traces with poses, results repeat exactly for a seed."""

from __future__ import annotations

import asyncio
import contextlib
import random

import numpy as np
from agent_fakes import SECRET, ScriptedMaster, agent_config, receive, spec

import simulator.body as sim_body
import simulator.scenarios as scenarios
import simulator.world as world_module
from minimize_surprise.network import GenomeLayout
from minimize_surprise.wire import Evaluate, Result, genome_to_bytes
from robot_agent.agent import Agent

ROBOTS = 3
STEPS = 30


async def run_swarm(seed: int) -> list[Result]:
    """One recorded evaluation of the same random genome on every robot of a fresh world."""
    world = world_module.World(scenarios.scenario_config("basic", {"robots": ROBOTS}), seed)
    swarm = sim_body.SimSwarm(world)
    bodies = swarm.bodies()
    master = ScriptedMaster()
    await master.start()
    network = spec(world.sensors)
    g = np.random.default_rng(seed).uniform(-1, 1, GenomeLayout(network).size)
    results: list[Result] = []
    try:
        async with contextlib.AsyncExitStack() as stack:
            for body in bodies:
                # Every body joins the lockstep before any agent runs (SimSwarm.attach's advice).
                await stack.enter_async_context(body)
            for i, body in enumerate(bodies):
                config = agent_config(master.port, robot_id=f"sim-{i}")
                agent = Agent(config, body, body.clock, SECRET, rng=random.Random(i))
                await stack.enter_async_context(agent)
                stack.push_async_callback(_cancel, asyncio.create_task(agent.run()))
            streams = {}
            for _ in bodies:
                stream = await master.next()
                hello = await master.welcome(stream)
                streams[hello.robot_id] = stream
            for eid, name in enumerate(sorted(streams)):
                await streams[name].send(
                    Evaluate(
                        evaluation_id=eid,
                        genome=genome_to_bytes(g),
                        spec=network,
                        steps=STEPS,
                        step_period=0.1,
                        record=True,
                    )
                )
            for name in sorted(streams):
                result = await receive(streams[name], timeout=10)
                assert isinstance(result, Result), result
                results.append(result)
    finally:
        await master.close()
    return results


async def _cancel(task: asyncio.Task[None]) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


async def test_simulated_swarm_evaluates_in_lockstep_and_repeats_for_a_seed():
    first = await run_swarm(seed=4)
    assert len(first) == ROBOTS
    for result in first:
        assert result.stats.steps_run == STEPS and result.stats.overruns == 0
        assert 0.0 <= result.fitness <= 1.0
        trace = result.trace
        assert trace is not None and trace.poses is not None and trace.steps == STEPS
        # Each robot stands somewhere different; over the run at least one of them moved.
    poses = [r.trace.array("poses") for r in first]
    assert len({tuple(p[0]) for p in poses}) == ROBOTS
    assert any((p[0] != p[-1]).any() for p in poses)
    again = await run_swarm(seed=4)
    assert [r.fitness for r in again] == [r.fitness for r in first]
    assert [r.trace.poses for r in again] == [r.trace.poses for r in first]
