"""The master's telemetry against a real broker: the retained run status, and an evolution that
the broker's loss and return do not touch."""

from __future__ import annotations

import asyncio
import contextlib
import io
import random

from master_helpers import (
    SECRET,
    assert_matches_reference,
    close,
    experiment,
    make_robots,
    master_config,
    robot_ids,
    run_with,
)
from rich.console import Console
from telemetry_helpers import eventually

from master_service import Master, Progress
from reporting.watch import SwarmState, render
from robot_agent.agent import Agent
from robot_agent.config import AgentConfig, BackoffConfig
from robot_agent.config import MasterConfig as LinkConfig
from simulator.body import SimSwarm
from simulator.scenarios import scenario_config
from simulator.world import World
from telemetry.config import TelemetryConfig

FAST = BackoffConfig(initial=0.02, max=0.1, jitter=0.5)
ROBOTS = 3


def telemetry(url: str) -> TelemetryConfig:
    return TelemetryConfig(broker=url, prefix="lab/run-1", reconnect=FAST)


async def test_the_run_status_is_published_retained(mosquitto, subscriber, tmp_path):
    exp = experiment(evaluations=6)
    config = master_config(exp, telemetry=telemetry(mosquitto.url))
    async with subscriber(mosquitto.port, "lab/run-1") as live:
        async with Master(config, tmp_path / "run", secret=SECRET) as master:
            robots = make_robots(master.port, ROBOTS)
            try:
                summary = await run_with(master, robots)
            finally:
                await close(robots)
            done = await live.wait_for("run/status", lambda p: p["phase"] == "done")
        stopped = await live.wait_for("run/status", lambda p: not p["online"])
    assert done == {
        "v": 1,
        "t": done["t"],
        "online": True,
        "run_id": "run",
        "phase": "done",
        "waiting": False,
        "evaluations": 6,
        "total": 6,
        "best_fitness": summary.best_fitness,
        "last_fitness": done["last_fitness"],
        "robots_connected": ROBOTS,
        "robots_expected": ROBOTS,
        "robots": robot_ids(ROBOTS),
        "failed_attempts": 0,
        "elapsed_s": done["elapsed_s"],
        "time_left_s": 0.0,
        "paused": None,
    }
    counts = [p["evaluations"] for p in live.payloads("run/status")]
    assert counts == sorted(counts) and counts[-1] == 6
    assert stopped["phase"] == "done" and stopped["robots_connected"] == 0
    # A watcher that comes later finds the last word of the run and of the master's client.
    async with subscriber(mosquitto.port, "lab/run-1") as late:
        assert (await late.wait_for("run/status"))["online"] is False
        assert (await late.wait_for("master/status"))["online"] is False


async def test_the_evolution_goes_on_while_the_broker_is_away(mosquitto, subscriber, tmp_path):
    exp = experiment(evaluations=16)
    config = master_config(exp, telemetry=telemetry(mosquitto.url))
    run_dir = tmp_path / "run"
    events: list[str] = []

    def outage(progress: Progress) -> None:
        # Blocking the event loop for the few milliseconds a stop or start takes is the test's
        # doing; the master under test only sees its broker vanish and return.
        if progress.evaluations >= 4 and "stopped" not in events:
            events.append("stopped")
            mosquitto.stop()
        elif progress.evaluations >= 10 and "started" not in events:
            events.append("started")
            mosquitto.start()

    async with Master(config, run_dir, secret=SECRET, on_progress=outage) as master:
        robots = make_robots(master.port, ROBOTS)
        try:
            summary = await run_with(master, robots)
        finally:
            await close(robots)
        assert events == ["stopped", "started"]
        pub = master.telemetry
        assert pub is not None
        await eventually(lambda: pub.connections >= 2 and pub.pending == 0)
        # The restarted broker knew nothing; the master published its status again.
        async with subscriber(mosquitto.port, "lab/run-1") as late:
            status = await late.wait_for("run/status", lambda p: p["phase"] == "done")
        assert status["evaluations"] == 16 and status["best_fitness"] == summary.best_fitness
    # Exactly the evaluations of an undisturbed run.
    assert summary.failed_attempts == 0
    assert_matches_reference(run_dir, exp, robot_ids(ROBOTS))


async def test_an_unreachable_broker_leaves_the_run_alone(closed_port, tmp_path, caplog):
    exp = experiment(evaluations=6)
    url = f"mqtt://127.0.0.1:{closed_port}"
    config = master_config(exp, telemetry=TelemetryConfig(broker=url, reconnect=FAST))
    async with Master(config, tmp_path / "run", secret=SECRET) as master:
        robots = make_robots(master.port, ROBOTS)
        try:
            summary = await run_with(master, robots)
        finally:
            await close(robots)
        await asyncio.sleep(0.2)  # several more attempts in the background
    assert summary.evaluations == 6
    assert_matches_reference(tmp_path / "run", exp, robot_ids(ROBOTS))
    warnings = [r.getMessage() for r in caplog.records if r.name.startswith("telemetry")]
    assert len(warnings) == 1 and "cannot reach the broker" in warnings[0]


async def test_a_simulated_swarm_as_the_watcher_sees_it(mosquitto, subscriber, tmp_path):
    # Master and three agents on simulated bodies, all publishing; the watcher's state is fed
    # with everything that arrived and shows every robot.
    exp = experiment(evaluations=4, evaluation_steps=10, post_evaluation_steps=10, robots=ROBOTS)
    config = master_config(exp, telemetry=telemetry(mosquitto.url))
    swarm = SimSwarm(World(scenario_config("basic", {"robots": ROBOTS}), 5), attach_all=True)
    agent_telemetry = TelemetryConfig(
        broker=mosquitto.url, prefix="lab/run-1", rate_hz=10, reconnect=FAST
    )

    async def cancel(task: asyncio.Task[None]) -> None:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task

    async with subscriber(mosquitto.port, "lab/run-1") as live:
        async with contextlib.AsyncExitStack() as stack:
            master = await stack.enter_async_context(
                Master(config, tmp_path / "run", secret=SECRET)
            )
            for i in range(ROBOTS):
                body = await stack.enter_async_context(swarm.body(i))
                agent_config = AgentConfig(
                    robot_id=f"sim-{i}",
                    master=LinkConfig(host="127.0.0.1", port=master.port, secret_file="unused"),
                    reconnect=BackoffConfig(initial=0.01, max=0.05, jitter=0.5),
                    telemetry=agent_telemetry,
                )
                agent = Agent(agent_config, body, body.clock, SECRET, rng=random.Random(i))
                await stack.enter_async_context(agent)
                stack.push_async_callback(cancel, asyncio.create_task(agent.run()))
            summary = await asyncio.wait_for(master.run(), 30)
            await live.wait_for("run/status", lambda p: p["phase"] == "done")
            for i in range(ROBOTS):
                # 4 evaluations and the post-evaluation, each summarised by every robot.
                await eventually(lambda i=i: len(live.payloads(f"robot/sim-{i}/evaluation")) == 5)
        for i in range(ROBOTS):
            await live.wait_for(f"robot/sim-{i}/status", lambda p: not p["online"])

    assert summary.evaluations == 4
    for i in range(ROBOTS):
        evaluations = live.payloads(f"robot/sim-{i}/evaluation")
        assert [e["steps"] for e in evaluations] == [10, 10, 10, 10, 10]
        assert all(0.0 <= e["fitness"] <= 1.0 for e in evaluations)
        samples = live.payloads(f"robot/sim-{i}/sample")
        assert len(samples) == 50 and all(len(s["sensors"]) == len(s["names"]) for s in samples)
    state = SwarmState(prefix="lab/run-1")
    for topic, payload, _ in live.messages:
        assert state.apply(topic, payload), topic
    console = Console(record=True, width=200, file=io.StringIO())
    console.print(render(state))
    out = console.export_text()
    assert "done (master stopped)" in out and "4/4" in out
    assert all(f"sim-{i}" in out for i in range(ROBOTS))
