"""The agent against the real thing: Debian's ``asebamedulla`` with Aseba Playground's Thymios.

What a lab sees: the failsafe program loads for an agent whose /tmp is private (systemd's
PrivateTmp), medulla's own reason is reported when a program does not load, the failsafe stops a
SIGKILLed agent's robot and SIGTERM stops it at once, a medulla restarted under a driving agent
gets the program again and the robot drives smoothly, a robot that goes away is reported to the
master and recovered when it is back, and a short run with two robots completes although one
agent is killed and restarted.

Agents run as separate processes (``python -m robot_agent.cli``); the master is either the test
itself (a few scripted lines, for a genome that drives straight at a known speed) or
``surprise-master run``.
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml
from aseba_stack import (
    Bus,
    Medulla,
    Observer,
    Playground,
    free_port,
    private_tmp_command,
    require_aseba,
)

import drivers.thymio as thymio_module
from drivers.config import ThymioConfig
from drivers.medulla_locale import LOCALE_FIX
from drivers.thymio import ThymioBase
from minimize_surprise.errors import HardwareError
from minimize_surprise.wire import Evaluate, Failed, Result, genome_to_bytes

pytestmark = pytest.mark.slow

SECRET = b"real aseba secret"
#: A 10 Hz evaluation much longer than any test (under the robots' loop.max_steps): the robot
#: drives until the test acts.
LONG = 30_000
#: Seconds to wait for an agent process to connect and for its robot to move.
AGENT_TIMEOUT = 30.0
#: The failsafe's timeout in the agents' configuration (seconds).
FAILSAFE_TIMEOUT = 1.0


@dataclass
class Robot:
    """One Playground Thymio with its own bus and (supervised) medulla."""

    bus: Bus
    medulla: Medulla
    robot_port: int

    @property
    def address(self) -> str:
        return self.bus.address


@dataclass
class Lab:
    """Playground, robots, and the agent processes of one test."""

    directory: Path
    playground: Playground
    robots: list[Robot]
    agents: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)
    logs: list[Path] = field(default_factory=list)

    def agent_config(self, index: int, master_port: int, **thymio: object) -> Path:
        """Write robot ``index``'s agent configuration; its path."""
        secret = self.directory / "secret.key"
        secret.write_bytes(SECRET)
        config = {
            "robot_id": f"thymio-{index}",
            "master": {"host": "127.0.0.1", "port": master_port, "secret_file": str(secret)},
            "body": {
                "thymio": {
                    "bus": self.robots[index].address,
                    "failsafe": True,
                    "failsafe_timeout": FAILSAFE_TIMEOUT,
                    **thymio,
                }
            },
            # Playground's floor is white: the ground rule would stop every straight drive.
            "safety": {"profile": "stop", "ground_threshold": 1.0, "stop_ir_threshold": 1.0},
            "reconnect": {"initial": 0.1, "max": 1.0},
        }
        path = self.directory / f"agent-{index}.yaml"
        path.write_text(yaml.safe_dump(config))
        return path

    def start_agent(self, index: int, config: Path, *extra: str) -> subprocess.Popen[bytes]:
        """Start ``surprise-agent`` for robot ``index`` as a process of its own."""
        name = f"agent-{index}"
        log = self.directory / f"{name}.{sum(p.name.startswith(name) for p in self.logs)}.log"
        self.logs.append(log)
        with open(log, "wb") as out:
            process = subprocess.Popen(
                [sys.executable, "-m", "robot_agent.cli", "--config", str(config), *extra],
                stdout=out,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
        self.agents[name] = process
        return process

    def output(self, name: str) -> str:
        """Everything agent ``name`` has logged, over all its starts."""
        return "".join(
            p.read_text(errors="replace") for p in self.logs if p.name.startswith(f"{name}.")
        )

    def report(self) -> str:
        """The tail of every log, for a failing test."""
        parts = []
        for path in [*self.logs, *sorted(self.directory.rglob("*.log"))]:
            if path.exists():
                lines = path.read_text(errors="replace").splitlines()[-30:]
                parts.append(f"----- {path.name}\n" + "\n".join(lines))
        return "\n".join(dict.fromkeys(parts))


@contextlib.asynccontextmanager
async def lab_of(
    tmp_path: Path, robots: int, medulla_env: dict[str, str] | None = None
) -> AsyncIterator[Lab]:
    """Playground with ``robots`` Thymios, each behind its own medulla on its own bus (with
    ``medulla_env`` added to medulla's environment)."""
    require_aseba()
    ports = [free_port() for _ in range(robots)]
    playground = Playground(tmp_path / "playground", ports)
    lab = Lab(tmp_path, playground, [])
    try:
        await playground.start()
        for index, port in enumerate(ports):
            bus = Bus(tmp_path / f"bus-{index}")
            bus.start()
            medulla = Medulla(tmp_path / f"medulla-{index}", bus.address, port, medulla_env)
            lab.robots.append(Robot(bus, medulla, port))
            await medulla.start()
        for robot in lab.robots:
            await connected(robot)
        yield lab
    except BaseException:
        print(lab.report())
        raise
    finally:
        for process in lab.agents.values():
            if process.poll() is None:
                process.terminate()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    process.wait(timeout=10)
                if process.poll() is None:
                    process.kill()
        for robot in lab.robots:
            await robot.medulla.stop()
            robot.bus.stop()
        playground.stop()


#: Seconds a fresh medulla gets to list its Playground robot. One that connected while Playground
#: was still starting may never list it (it asks for the node's description once).
LIST_TIMEOUT = 5.0


async def connected(robot: Robot, attempts: int = 4) -> None:
    """Wait until the robot's medulla lists the node, restarting a medulla that never will."""
    async with Observer(robot.address) as observer:
        for _ in range(attempts - 1):
            with contextlib.suppress(TimeoutError):
                await observer.ready(LIST_TIMEOUT)
                return
            robot.medulla.end()
            await asyncio.sleep(0.2)
        await observer.ready(LIST_TIMEOUT)


async def until(condition, timeout: float, what: str, lab: Lab, poll: float = 0.02):
    """Await ``condition()`` (a coroutine function) until truthy; its value. Fails with logs."""
    deadline = time.monotonic() + timeout
    while True:
        with contextlib.suppress(RuntimeError):
            value = await condition()
            if value:
                return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what}\n{lab.report()}")
        await asyncio.sleep(poll)


def straight(evaluation_id: int, steps: int = LONG) -> Evaluate:
    """An evaluation of a genome that drives both wheels at tanh(1) = 0.76 of full speed."""
    from agent_fakes import genome, spec

    network = spec()
    return Evaluate(
        evaluation_id=evaluation_id,
        genome=genome_to_bytes(genome(network, speed_bias=1.0)),
        spec=network,
        steps=steps,
        step_period=0.1,
    )


#: The motor target of :func:`straight` with the default speed scale (265 units).
STRAIGHT_TARGET = round(0.7615941559557649 * 265)


# --------------------------------------------------------------------------- the program


async def test_the_failsafe_loads_for_an_agent_whose_tmp_is_private(tmp_path: Path):
    """Under systemd the agent has PrivateTmp=yes and medulla does not: a program written to the
    agent's /tmp is not there for medulla. The installed file is."""
    async with lab_of(tmp_path, 1) as lab:
        address = lab.robots[0].address
        script = (
            "import asyncio, sys\n"
            "from drivers.config import ThymioConfig\n"
            "from drivers.thymio import ThymioBase\n"
            "async def main():\n"
            "    base = ThymioBase(ThymioConfig(bus=sys.argv[1], failsafe=True))\n"
            "    await base.open()\n"
            "    print('attached', base.attached, base.failsafe_active)\n"
            "    await base.close()\n"
            "asyncio.run(main())\n"
        )
        command = private_tmp_command(
            [sys.executable, "-c", script, address], tmp_path / "private-tmp"
        )
        result = await asyncio.to_thread(
            subprocess.run, command, capture_output=True, text=True, timeout=60
        )
        assert result.returncode == 0, result.stdout + result.stderr
        assert "True" in result.stdout
        async with Observer(address) as observer:
            assert await observer.get("heartbeat") == [0]  # medulla knows the program's variable


async def test_a_missing_locale_is_named_with_the_command_that_installs_it(tmp_path: Path):
    """Debian's medulla aborts loading any program without the en_US.UTF-8 locale; glibc's
    LOCPATH pointed at an empty directory makes this machine lack every locale, for medulla and
    for the driver alike, as on a fresh Pi."""
    no_locales = tmp_path / "no-locales"
    no_locales.mkdir()
    env = {"LOCPATH": str(no_locales)}
    async with lab_of(tmp_path, 1, medulla_env=env) as lab:
        script = (
            "import asyncio, sys\n"
            "from drivers.config import ThymioConfig\n"
            "from drivers.thymio import ThymioBase\n"
            "from minimize_surprise.errors import HardwareError\n"
            "async def main():\n"
            "    base = ThymioBase(ThymioConfig(bus=sys.argv[1], failsafe=True))\n"
            "    try:\n"
            "        await base.open()\n"
            "    except HardwareError as exc:\n"
            "        print(exc)\n"
            "    finally:\n"
            "        await base.close()\n"
            "asyncio.run(main())\n"
        )
        result = await asyncio.to_thread(
            subprocess.run,
            [sys.executable, "-c", script, lab.robots[0].address],
            capture_output=True,
            text=True,
            timeout=60,
            env={**os.environ, **env},
        )
        log = (lab.robots[0].medulla.directory / "medulla.0.log").read_text(errors="replace")
    assert "_S_create_c_locale name not valid" in log  # medulla's own abort, not a stand-in
    (line,) = result.stdout.strip().splitlines()
    assert "the en_US.UTF-8 locale it needs is not installed" in line
    assert line.endswith(f"run: {LOCALE_FIX}")


async def test_medulla_s_own_reason_is_reported_when_a_program_does_not_load(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    async with lab_of(tmp_path, 1) as lab:
        monkeypatch.setattr(
            thymio_module, "program_path", lambda *args: str(tmp_path / "nowhere.aesl")
        )
        base = ThymioBase(ThymioConfig(bus=lab.robots[0].address, failsafe=True))
        with pytest.raises(HardwareError, match=r"nowhere\.aesl does not exists"):
            await base.open()


# --------------------------------------------------------------------------- stopping


async def test_the_failsafe_stops_a_killed_agent_and_sigterm_stops_at_once(tmp_path: Path):
    from agent_fakes import ScriptedMaster

    master = ScriptedMaster()
    await master.start()
    try:
        async with lab_of(tmp_path, 1) as lab, Observer(lab.robots[0].address) as robot:
            config = lab.agent_config(0, master.port)

            async def driving() -> bool:
                return await robot.targets() == (STRAIGHT_TARGET, STRAIGHT_TARGET)

            async def stopped() -> bool:
                return await robot.targets() == (0, 0)

            agent = lab.start_agent(0, config)
            stream = await master.next(AGENT_TIMEOUT)
            await master.welcome(stream, SECRET)
            await stream.send(straight(1))
            await until(driving, AGENT_TIMEOUT, "the robot to drive", lab)

            # SIGKILL: no clean-up at all; only the program on the Thymio can stop it.
            agent.kill()
            killed = time.monotonic()
            await until(stopped, 5.0, "the failsafe to stop the robot", lab)
            failsafe_delay = time.monotonic() - killed
            assert failsafe_delay < FAILSAFE_TIMEOUT + 0.5, failsafe_delay
            print(f"failsafe stop after SIGKILL: {failsafe_delay:.2f} s")
            # systemd's ExecStopPost: confirmed by the robot, whatever medulla knows.
            stop_once = await asyncio.to_thread(
                subprocess.run,
                [sys.executable, "-m", "robot_agent.cli", "--config", str(config), "--stop-motors"],
                capture_output=True,
                text=True,
                timeout=30,
            )
            assert stop_once.returncode == 0, stop_once.stdout + stop_once.stderr

            agent = lab.start_agent(0, config)
            stream = await master.next(AGENT_TIMEOUT)
            await master.welcome(stream, SECRET)
            await stream.send(straight(2))
            await until(driving, AGENT_TIMEOUT, "the robot to drive again", lab)
            agent.send_signal(signal.SIGTERM)
            terminated = time.monotonic()
            await until(stopped, 2.0, "SIGTERM to stop the robot", lab)
            sigterm_delay = time.monotonic() - terminated
            print(f"stop after SIGTERM: {sigterm_delay:.2f} s")
            assert await asyncio.to_thread(agent.wait, 10) == 0
            assert sigterm_delay < 0.5, sigterm_delay
    finally:
        await master.close()


# --------------------------------------------------------------------------- medulla and robot


async def test_a_medulla_restarted_under_a_driving_agent(tmp_path: Path):
    """The new medulla does not know the failsafe's heartbeat; the program still running on the
    Thymio would zero the motor targets every 100 ms. The agent notices the new medulla, fails
    that evaluation, loads the program into the new medulla, and then drives smoothly."""
    from agent_fakes import ScriptedMaster

    master = ScriptedMaster()
    await master.start()
    try:
        async with lab_of(tmp_path, 1) as lab, Observer(lab.robots[0].address) as robot:
            medulla = lab.robots[0].medulla
            lab.start_agent(0, lab.agent_config(0, master.port))
            stream = await master.next(AGENT_TIMEOUT)
            await master.welcome(stream, SECRET)
            await stream.send(straight(1))

            async def driving() -> bool:
                return await robot.targets() == (STRAIGHT_TARGET, STRAIGHT_TARGET)

            await until(driving, AGENT_TIMEOUT, "the robot to drive", lab)
            medulla.end()
            failed = await asyncio.wait_for(stream.receive(), 15)
            assert isinstance(failed, Failed) and failed.evaluation_id == 1, failed
            assert failed.reason.startswith("robot-unreachable"), failed.reason
            await until(
                lambda: _contains(lab, "agent-0", "robot reachable again"),
                30,
                "the agent to attach to the new medulla",
                lab,
                poll=0.1,
            )
            await stream.send(straight(2))
            await until(driving, 10, "the robot to drive again", lab)
            samples = []
            for _ in range(40):  # 2 s: twenty ticks of the program's timer
                samples.append(await robot.targets())
                await asyncio.sleep(0.05)
            assert set(samples) == {(STRAIGHT_TARGET, STRAIGHT_TARGET)}, samples
            assert (await robot.get("heartbeat"))[0] > 0  # the new medulla knows it
            assert medulla.starts == 2
    finally:
        await master.close()


async def test_a_robot_that_went_away_is_reported_and_recovered(tmp_path: Path):
    """Playground killed: the robot is gone, medulla keeps saying it is connected for seconds
    and never reconnects. The master is told, the log says so, the stops do not flood medulla,
    and once the robot is back the agent gets a fresh medulla (it ends the stale one) and
    evaluates again."""
    from agent_fakes import ScriptedMaster

    master = ScriptedMaster()
    await master.start()
    try:
        async with lab_of(tmp_path, 1) as lab:
            medulla = lab.robots[0].medulla
            lab.start_agent(0, lab.agent_config(0, master.port))
            stream = await master.next(AGENT_TIMEOUT)
            await master.welcome(stream, SECRET)
            await stream.send(straight(1))
            async with Observer(lab.robots[0].address) as robot:
                await until(lambda: _driving(robot), AGENT_TIMEOUT, "the robot to drive", lab)
            lab.playground.kill()
            failed = await asyncio.wait_for(stream.receive(), 10)
            assert isinstance(failed, Failed) and failed.reason.startswith("robot-unreachable")
            await stream.send(straight(2, steps=10))
            refused = await asyncio.wait_for(stream.receive(), 10)
            assert isinstance(refused, Failed) and refused.reason.startswith("robot-unreachable")
            assert "robot unreachable" in lab.output("agent-0")
            monitor = await _monitor_set_variable(lab.robots[0].address)
            await asyncio.sleep(4.0)
            writes = monitor.stop()
            # A stop is two writes. The watchdog retries at most once a second, and recovery
            # tries at growing intervals (1, 2, 4 s): some 12 writes in 4 s, where retrying on
            # every watchdog check would be some 320.
            print(f"SetVariable calls in 4 s while the robot is gone: {writes}")
            assert writes <= 20, writes
            await lab.playground.start()  # the robot is back
            await until(
                lambda: _contains(lab, "agent-0", "robot reachable again"),
                60,
                "the robot to be recovered",
                lab,
                poll=0.2,
            )
            assert medulla.starts >= 2  # the stale medulla was ended and a fresh one started
            await stream.send(straight(3, steps=10))
            result = await asyncio.wait_for(stream.receive(), 15)
            assert isinstance(result, Result) and result.evaluation_id == 3, result
    finally:
        await master.close()


async def _driving(robot: Observer) -> bool:
    return await robot.targets() == (STRAIGHT_TARGET, STRAIGHT_TARGET)


async def _contains(lab: Lab, name: str, text: str) -> bool:
    return text in lab.output(name)


class _Monitor:
    def __init__(self, process: subprocess.Popen[bytes], path: Path) -> None:
        self.process = process
        self.path = path

    def stop(self) -> int:
        self.process.terminate()
        self.process.wait()
        return self.path.read_text(errors="replace").count("member=SetVariable")


async def _monitor_set_variable(address: str) -> _Monitor:
    """Count the SetVariable calls on a bus from now on (``dbus-monitor``)."""
    from needs import require_binary

    require_binary("dbus-monitor")
    path = Path(os.environ.get("TMPDIR", "/tmp")) / f"monitor-{os.getpid()}-{time.time_ns()}.txt"
    out = open(path, "wb")  # noqa: SIM115 - handed to the process
    process = subprocess.Popen(
        ["dbus-monitor", "--address", address, "interface='ch.epfl.mobots.AsebaNetwork'"],
        stdout=out,
        stderr=subprocess.DEVNULL,
    )
    out.close()
    await asyncio.sleep(0.5)  # let it subscribe
    return _Monitor(process, path)


# --------------------------------------------------------------------------- a whole run

EVALUATIONS = 8
STEPS = 10


async def test_a_short_run_with_two_robots_survives_a_killed_agent(tmp_path: Path):
    async with lab_of(tmp_path, 2) as lab:
        port = free_port()
        configs = [lab.agent_config(i, port) for i in range(2)]
        run = tmp_path / "run"
        master_config = tmp_path / "master.yaml"
        master_config.write_text(
            yaml.safe_dump(
                {
                    "experiment": {
                        "robots": 2,
                        "seed": 3,
                        "evaluation_steps": STEPS,
                        "post_evaluation_steps": STEPS,
                        "evolution": {"evaluations": EVALUATIONS},
                    },
                    "host": "127.0.0.1",
                    "port": port,
                    "secret_file": str(tmp_path / "secret.key"),
                    "allowed_robots": ["thymio-0", "thymio-1"],
                    "round_margin": 3.0,
                    "heartbeat_interval": 1.0,
                }
            )
        )
        with open(tmp_path / "master.out", "wb") as out:
            master = subprocess.Popen(
                [sys.executable, "-m", "master_service", "run", "--config", str(master_config),
                 "--out", str(run)],
                stdout=out,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
            )  # fmt: skip
        try:
            for index in range(2):
                lab.start_agent(index, configs[index])

            async def rows() -> int:
                return len(_rows(run)) >= 3

            await until(rows, 60, "three evaluations", lab, poll=0.1)
            lab.agents["agent-1"].kill()
            await asyncio.sleep(1.0)
            lab.start_agent(1, configs[1])
            code = await asyncio.to_thread(master.wait, 120)
            assert code == 0, lab.report()
        finally:
            if master.poll() is None:
                master.kill()
        done = _rows(run)
        assert [int(r["evaluation"]) for r in done] == list(range(1, EVALUATIONS + 1))
        checkpoint = json.loads((run / "checkpoint.json").read_text())
        assert checkpoint["phase"] == "done"
        assert lab.output("agent-1").count("welcomed into run") >= 2


def _rows(run: Path) -> list[dict[str, str]]:
    path = run / "evaluations.csv"
    if not path.exists():
        return []
    with open(path, newline="", encoding="utf-8") as file:
        return [row for row in csv.DictReader(file) if None not in row.values()]
