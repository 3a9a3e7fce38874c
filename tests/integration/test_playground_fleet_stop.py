"""``surprise-master fleet stop`` against the real stack: two Aseba Playground Thymios, each
behind Debian's own ``asebamedulla`` on its own D-Bus, each with a ``surprise-agent`` process.

No run is going. Something else left both robots driving (a person's ``asebacmd``, a crashed
tool: here a third D-Bus client writes the motor targets), and their failsafe program is not
loaded, so nothing on the Thymio would stop them. The command, run as a person runs it, serves
the agents, each stops its robot through medulla, and the command lists both as confirmed and
exits 0; the motor targets the robots hold are then 0 (read through medulla, as ``asebacmd``
would)."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from aseba_stack import Observer, free_port
from test_real_aseba import AGENT_TIMEOUT, SECRET, lab_of, until

pytestmark = pytest.mark.slow

#: What the stray tool wrote: about 8 cm/s forward.
DRIVING = 200
#: Seconds the command waits for the agents: they retry every second at most
#: (``reconnect.max`` in the lab's agent files).
WAIT = 20.0


async def _set_targets(robot: Observer, left: int, right: int) -> None:
    await robot.call("SetVariable", "ssan", (robot.node, "motor.left.target", [left]))
    await robot.call("SetVariable", "ssan", (robot.node, "motor.right.target", [right]))


async def test_fleet_stop_stops_playground_robots_behind_real_medulla(tmp_path: Path):
    port = free_port()
    async with lab_of(tmp_path, 2) as lab:
        observers = [Observer(robot.address) for robot in lab.robots]
        for observer in observers:
            await observer.__aenter__()
        try:
            for index in range(2):
                config = lab.agent_config(index, port, failsafe=False)
                lab.start_agent(index, config)

            async def agents_ready() -> bool:
                # Each agent has its robot and is trying to reach a master that is not there.
                return all("connect" in lab.output(f"agent-{i}").lower() for i in range(2))

            await until(agents_ready, AGENT_TIMEOUT, "both agents to try the master", lab)
            for observer in observers:
                await _set_targets(observer, DRIVING, DRIVING)

            async def driving() -> bool:
                targets = [await observer.targets() for observer in observers]
                return targets == [(DRIVING, DRIVING)] * 2

            await until(driving, 5.0, "both robots to drive", lab)
            await asyncio.sleep(0.5)
            assert await driving(), "something stopped the robots before the command"

            master = tmp_path / "master.yaml"
            (tmp_path / "secret").write_bytes(SECRET)
            (tmp_path / "secret").chmod(0o600)
            master.write_text(
                yaml.safe_dump(
                    {
                        "experiment": {"robots": 2, "seed": 1},
                        "host": "127.0.0.1",
                        "port": port,
                        "allowed_robots": ["thymio-0", "thymio-1"],
                        "secret_file": "secret",
                    }
                )
            )
            command = [
                sys.executable, "-m", "master_service", "fleet", "stop",
                "--config", str(master), "--timeout", str(WAIT),
            ]  # fmt: skip
            done = await asyncio.to_thread(
                subprocess.run, command, capture_output=True, text=True, timeout=WAIT + 30
            )
            out = done.stdout + done.stderr
            assert done.returncode == 0, out + lab.report()
            assert "stopped (confirmed): thymio-0, thymio-1" in out, out
            assert "did not answer: none" in out, out
            assert [await observer.targets() for observer in observers] == [(0, 0)] * 2
        finally:
            for observer in observers:
                await observer.__aexit__(None, None, None)
