"""The master with the real robot agent on simulated bodies, over loopback TCP: both sides of the
protocol as built, the way the ``sim`` command will run them (one event loop, lockstep world)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import random

import pytest
from master_helpers import SECRET, experiment, master_config, read_csv

import robot_agent.agent as agent_module
import robot_agent.config as agent_config_module
import simulator.body as sim_body
import simulator.scenarios as scenarios
import simulator.world as world_module
from master_service import Master
from reporting.report import write_report

ROBOTS = 3


async def _cancel(task: asyncio.Task[None]) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


async def test_a_simulated_swarm_of_agents_completes_a_run(tmp_path):
    exp = experiment(evaluations=6, evaluation_steps=10, post_evaluation_steps=20, robots=ROBOTS)
    world = world_module.World(scenarios.scenario_config("basic", {"robots": ROBOTS}), 5)
    swarm = sim_body.SimSwarm(world, attach_all=True)
    run = tmp_path / "run"
    cfg = agent_config_module
    async with contextlib.AsyncExitStack() as stack:
        master = await stack.enter_async_context(Master(master_config(exp), run, secret=SECRET))
        for i in range(ROBOTS):
            body = await stack.enter_async_context(swarm.body(i))
            config = cfg.AgentConfig(
                robot_id=f"sim-{i}",
                master=cfg.MasterConfig(host="127.0.0.1", port=master.port, secret_file="unused"),
                reconnect=cfg.BackoffConfig(initial=0.01, max=0.05, jitter=0.5),
            )
            agent = agent_module.Agent(config, body, body.clock, SECRET, rng=random.Random(i))
            await stack.enter_async_context(agent)
            stack.push_async_callback(_cancel, asyncio.create_task(agent.run()))
        summary = await asyncio.wait_for(master.run(), 30)
    rows = read_csv(run / "evaluations.csv")
    assert [int(r["evaluation"]) for r in rows] == list(range(1, 7))
    assert summary.failed_attempts == 0 and all(r["attempts"] == "1" for r in rows)
    for row in rows:
        fitnesses = [float(row[f"fitness_sim-{i}"]) for i in range(ROBOTS)]
        assert all(0.0 <= f <= 1.0 for f in fitnesses)
        assert float(row["fitness"]) == pytest.approx(sum(fitnesses) / ROBOTS)
    post = json.loads((run / "post_evaluation.json").read_text())
    assert post["steps"] == 20 and len(post["robots"]) == ROBOTS
    metrics = write_report(run)
    assert metrics["post_evaluation"]["behaviour"]["distance_covered"] >= 0.0
    assert (run / "plots" / "trajectories.png").exists()
