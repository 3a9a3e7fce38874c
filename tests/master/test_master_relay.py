"""A relay between a robot and the master forwards the handshake, then tampers: whatever it adds,
replays or sends back is detected, that session is closed, and nothing of it is counted."""

from __future__ import annotations

import asyncio

import pytest
from master_helpers import (
    SECRET,
    assert_matches_reference,
    close,
    experiment,
    make_robots,
    master_config,
    robot_ids,
)

from master_service import Master
from minimize_surprise.wire import (
    Evaluate,
    EvaluationStats,
    Ping,
    Pong,
    Result,
)
from relay import Relay, tagged_message
from standins.scripted_robots import ScriptedRobot
from transport.framing import encode


@pytest.fixture
async def relay_to():
    relays: list[Relay] = []

    async def start(port: int) -> Relay:
        relay = Relay(port)
        await relay.start()
        relays.append(relay)
        return relay

    yield start
    for relay in relays:
        await relay.close()


def log_of(tmp_path) -> str:
    return (tmp_path / "run" / "master.log").read_text()


async def test_a_result_forged_by_a_relay_closes_the_session_and_is_not_counted(tmp_path, relay_to):
    exp = experiment(evaluations=3)
    async with Master(master_config(exp), tmp_path / "run", secret=SECRET) as master:
        relay = await relay_to(master.port)
        robots = make_robots(master.port, 3)
        # r1 goes through the relay and answers late, so that the forgery arrives first.
        robots[1] = ScriptedRobot("r1", SECRET, relay.port, index=1, delay=0.2)
        run = asyncio.create_task(master.run())
        await asyncio.gather(*(r.connect() for r in robots))
        link = relay.connections[0]

        def evaluate_seen() -> Evaluate | None:
            for frame in link.to_client:
                if isinstance(msg := tagged_message(frame), Evaluate):
                    return msg
            return None

        await relay.wait_for(lambda: evaluate_seen() is not None)
        forged = Result(
            evaluation_id=evaluate_seen().evaluation_id,
            fitness=1.0,
            stats=EvaluationStats(steps_run=1, overruns=0, interventions={}),
        )
        link.inject_to_server(encode(forged))
        await asyncio.wait_for(robots[1].closed.wait(), 5)
        await robots[1].connect()  # the real robot comes back (through the relay again)
        summary = await asyncio.wait_for(run, 15)
        await close(robots)
    # The forged fitness of 1.0 counted nowhere: the run is the reference run.
    assert summary.failed_attempts == 1
    assert_matches_reference(tmp_path / "run", exp, robot_ids(3))
    assert "robot r1: frame 0 fails authentication" in log_of(tmp_path)


@pytest.mark.parametrize("tamper", ["replay", "reflect"])
async def test_a_frame_replayed_or_sent_back_by_a_relay_closes_the_session(
    tmp_path, relay_to, tamper
):
    # heartbeat 0.1 s: the master pings and the robot answers within a fraction of a second.
    config = master_config(heartbeat_interval=0.1)
    async with Master(config, tmp_path / "run", secret=SECRET) as master:
        relay = await relay_to(master.port)
        robot = ScriptedRobot("r0", SECRET, relay.port)
        await robot.connect()
        link = relay.connections[0]
        pongs = lambda: [f for f in link.to_server if isinstance(tagged_message(f), Pong)]  # noqa: E731
        pings = lambda: [f for f in link.to_client if isinstance(tagged_message(f), Ping)]  # noqa: E731
        await relay.wait_for(lambda: pongs() and pings())
        if tamper == "replay":
            # The robot's own, correctly tagged answer, a second time.
            link.inject_to_server(pongs()[0])
        else:
            # The master's own ping, returned as if the robot had sent it.
            link.inject_to_server(pings()[-1])
        await asyncio.wait_for(robot.closed.wait(), 5)
        assert master.connected_robots == []
    log = log_of(tmp_path)
    assert "robot r0: frame" in log and "fails authentication" in log
    assert "the session is closed" in log
