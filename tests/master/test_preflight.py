"""``surprise-master check``: real agents with real drivers over the fake asebamedulla and
emulated I2C, each robot with a fault a lab meets, against the check's real server on loopback.

The check finds the robot with a dead light sensor, the one that never connects, the one on a
floor the safety layer takes for an edge and the one with a flat battery, and passes the healthy
one; the command line prints the table or JSON and exits 1.
"""

from __future__ import annotations

import asyncio
import json
import random
import socket
import sys
from contextlib import AsyncExitStack
from pathlib import Path

import pytest

from drivers.clock import MonotonicClock
from drivers.compose import build_body
from drivers.config import BodyConfig, LightSensorConfig, MuxConfig, ThymioConfig
from drivers.thymio import VBAT
from master_service.config import MasterConfig
from master_service.preflight import format_table, run_check
from minimize_surprise.backoff import BackoffConfig
from minimize_surprise.config import ExperimentConfig
from minimize_surprise.provenance import software_commit
from robot_agent.agent import Agent
from robot_agent.config import AgentConfig
from robot_agent.config import MasterConfig as AgentMasterConfig
from standins.fake_i2c import FakeI2C, FakeTCA9548A, FakeTSL45315
from standins.fake_medulla import StaticThymioModel, private_bus, serve_fake_medulla

SECRET = b"preflight-secret"
#: The robot that never comes is waited for this long; the others connect in milliseconds.
CONNECT = 3.0
QUICK = BackoffConfig(initial=0.02, max=0.1, jitter=0.5)
ROBOTS = ["good", "dead-light", "bright", "flat", "missing"]


async def start_robot(
    stack: AsyncExitStack,
    robot_id: str,
    port: int,
    secret_file: str,
    *,
    reflected: tuple[int, int] = (300, 310),
    vbat: tuple[int, int] = (800, 800),
) -> tuple[Agent, FakeTCA9548A]:
    """An agent on a Thymio (fake medulla, ``_vbat`` declared) with two light sensors behind a
    multiplexer; returns the agent and the multiplexer (to break a sensor)."""
    address = await stack.enter_async_context(private_bus())
    model = StaticThymioModel(reflected=list(reflected))
    medulla = await stack.enter_async_context(serve_fake_medulla(address, model))
    medulla.native.add(VBAT)
    model.variables[VBAT] = list(vbat)
    i2c = FakeI2C()
    mux = i2c.bus(1).attach(0x70, FakeTCA9548A())
    mux.attach(0, 0x29, FakeTSL45315(lux=300.0))
    mux.attach(1, 0x29, FakeTSL45315(lux=450.0))
    body_config = BodyConfig(
        thymio=ThymioConfig(bus=address, timeout=1.0),
        light=[LightSensorConfig(mux=MuxConfig(channel=c)) for c in (0, 1)],
    )
    body = build_body(body_config, smbus_factory=i2c.smbus)
    await body.open()  # as the agent's start does, while every part answers
    stack.push_async_callback(body.close)
    config = AgentConfig(
        robot_id=robot_id,
        master=AgentMasterConfig(host="127.0.0.1", port=port, secret_file=secret_file),
        body=body_config,
        reconnect=QUICK,
    )
    agent = Agent(config, body, MonotonicClock(), SECRET, rng=random.Random(robot_id))
    await stack.enter_async_context(agent)
    return agent, mux


async def start_lab(stack: AsyncExitStack, port: int) -> None:
    """Four robots of the five the configuration names; each with what its name says."""
    robots = {
        "good": {},
        "dead-light": {},
        "bright": {"reflected": (1000, 990)},  # 0.98, 0.97 on a bright floor
        "flat": {"vbat": (680, 680)},  # 3.42 V
    }
    for robot_id, faults in robots.items():
        _, mux = await start_robot(stack, robot_id, port, "(in-process)", **faults)
        if robot_id == "dead-light":
            del mux.channels[1][0x29]  # it answered at start, then a cable came loose


def experiment() -> ExperimentConfig:
    return ExperimentConfig(robots=5, seed=1)


async def test_the_check_finds_what_keeps_a_robot_from_a_run():
    config = MasterConfig(experiment=experiment(), host="127.0.0.1", port=0, allowed_robots=ROBOTS)
    listening: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    async with AsyncExitStack() as stack:
        check = asyncio.create_task(
            run_check(config, SECRET, timeout=CONNECT, on_listening=listening.set_result)
        )
        await start_lab(stack, await listening)
        rows = await asyncio.wait_for(check, CONNECT + 30)

    by = {row.robot: row for row in rows}
    assert [row.robot for row in rows] == ROBOTS
    assert [row.robot for row in rows if row.fit] == ["good"]

    good = by["good"]
    assert good.connected and not good.problems
    assert good.battery_v == pytest.approx(1600 / 397.8, abs=1e-3)
    assert good.readings["light.0"] > 0 and good.readings["light.1"] > 0
    assert good.rtt_s is not None and good.rtt_s < 1.0
    assert good.clock_offset_s is not None and abs(good.clock_offset_s) < 1.0
    assert good.ground_rule == "ground >= 0.55"

    (dead,) = by["dead-light"].problems
    assert dead.startswith("light.1 does not answer")
    assert "light.0" in by["dead-light"].readings  # one broken part hides nothing else

    (missing,) = by["missing"].problems
    assert not by["missing"].connected and "not connected within 3 s" in missing

    (floor,) = by["bright"].problems
    assert "ground sensors read 0.98, 0.97" in floor and "ground >= 0.55" in floor
    assert "too bright" in floor

    (flat,) = by["flat"].problems
    assert flat == "battery 3.42 V, below 3.60 V: swap it before the run"

    table = format_table(rows)
    assert table.splitlines()[0].split() == [
        "robot", "verdict", "software", "firmware", "link", "clock", "battery", "IR", "max",
        "ground", "light", "force",
    ]  # fmt: skip
    assert "good        fit" in table and "dead-light  UNFIT" in table
    assert good.firmware == 11 and good.commit == software_commit()  # the fake medulla's
    assert table.endswith("1 of 5 robots fit: fix the above")


async def test_the_command_prints_json_and_exits_1_when_a_robot_is_unfit(tmp_path: Path):
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    secret = tmp_path / "secret.key"
    secret.write_bytes(SECRET + b"\n")
    experiment_file = tmp_path / "experiment.yaml"
    experiment_file.write_text("scenario: basic\nsetting: lab\nrobots: 2\n")
    config_file = tmp_path / "master.yaml"
    config_file.write_text(
        f"experiment_file: {experiment_file}\nhost: 127.0.0.1\nport: {port}\n"
        f"secret_file: {secret}\nallowed_robots: [good, flat]\n"
    )
    async with AsyncExitStack() as stack:
        for robot_id, vbat in (("good", (800, 800)), ("flat", (680, 680))):
            await start_robot(stack, robot_id, port, str(secret), vbat=vbat)
        process = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "master_service", "check", str(config_file), "--json",
            "--timeout", "20",
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        out, err = await asyncio.wait_for(process.communicate(), 60)
    assert process.returncode == 1, err.decode()
    rows = json.loads(out)
    assert [(r["robot"], r["fit"]) for r in rows] == [("good", True), ("flat", False)]
    assert rows[1]["problems"] == ["battery 3.42 V, below 3.60 V: swap it before the run"]
    assert rows[0]["battery_v"] == pytest.approx(4.022, abs=1e-3)
