"""Separate processes, as in a lab: ``surprise-sim-robots`` serves simulated Thymios on private
D-Bus daemons, one ``surprise-agent`` process per robot drives one with the real Thymio driver,
and ``surprise-master`` runs the evolution, everything in real time.

Faults: an agent killed (SIGKILL) and restarted during the run, and the master killed and resumed;
either way the run completes with evaluations 1..E, none lost and none counted twice.

Every process is started as ``python -m <module>``, so PATH does not matter. Their output goes to
files under the test's directory; a failing test prints their tails (pytest shows the teardown's
output of failed tests only).
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from drivers.config import ThymioConfig
from drivers.thymio import ThymioBase
from needs import pids, require_binary
from robot_agent.config import load_agent_config

ROBOTS = 4
EVALUATIONS = 10
#: One evaluation is STEPS * 0.1 s of wall-clock time: short runs, yet several control steps.
STEPS = 10
SECRET = "separate-processes-secret\n"

#: Seconds for a process to be ready: importing numpy and dbus-fast and starting four
#: dbus-daemons takes a few seconds on a loaded two-core machine.
START_TIMEOUT = 30.0
#: Seconds for a whole run: 10 one-second evaluations and the post-evaluation take about 12 s;
#: the fault, the restart of a process and a loaded machine may double that.
RUN_TIMEOUT = 90.0
#: Seconds from SIGTERM to exit: the agents stop their motors, the server its daemons.
STOP_TIMEOUT = 10.0
#: Seconds between two looks at a file or a process (these are real processes in real time).
POLL = 0.1
#: Rows of evaluations.csv that must exist before a fault is injected: the run is under way.
ROWS_BEFORE_FAULT = 3
#: Lines of each process's output shown when a test fails.
TAIL_LINES = 25


# --------------------------------------------------------------------------- processes


class Processes:
    """Child processes of one test, each with its output in a file; see :meth:`stop_all`."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        directory.mkdir(parents=True, exist_ok=True)
        self.running: dict[str, subprocess.Popen[bytes]] = {}
        self.logs: list[Path] = []

    def start(self, name: str, module: str, *args: str) -> subprocess.Popen[bytes]:
        """Start ``python -m module args`` as ``name`` (a restart gets a new output file)."""
        assert name not in self.running or self.running[name].poll() is not None, name
        restarts = sum(p.name.startswith(f"{name}.") for p in self.logs)
        log = self.directory / f"{name}.{restarts}.log"
        self.logs.append(log)
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        with open(log, "wb") as out:
            process = subprocess.Popen(
                [sys.executable, "-m", module, *args],
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                cwd=self.directory.parent,
                env=env,
            )
        self.running[name] = process
        return process

    def pid(self, name: str) -> int:
        """The process id of ``name``."""
        return self.running[name].pid

    def alive(self, name: str) -> bool:
        """Whether ``name`` is still running."""
        return self.running[name].poll() is None

    def kill(self, name: str, signum: int = signal.SIGKILL) -> None:
        """Send ``signum`` to ``name``; after SIGKILL, wait until it is gone."""
        process = self.running[name]
        process.send_signal(signum)
        if signum == signal.SIGKILL:
            process.wait(timeout=STOP_TIMEOUT)

    def wait(self, name: str, timeout: float) -> int:
        """Wait for ``name`` to exit; its exit code (a timeout fails the test with the logs)."""
        try:
            return self.running[name].wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            pytest.fail(f"{name} did not exit within {timeout} s\n{self.report()}")

    def stop_all(self) -> None:
        """SIGTERM to every running process, then SIGKILL to those still there after a while;
        the dbus-daemons of a server that had to be killed are killed too."""
        live = {name: p for name, p in self.running.items() if p.poll() is None}
        daemons = {name: children(p.pid) for name, p in live.items()}
        for process in live.values():
            process.terminate()
        deadline = time.monotonic() + STOP_TIMEOUT
        for name, process in live.items():
            try:
                process.wait(timeout=max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
                for pid in daemons[name]:
                    _kill_pid(pid)

    def report(self) -> str:
        """The tail of every process's output."""
        parts = []
        for log in self.logs:
            lines = log.read_text(errors="replace").splitlines() if log.exists() else []
            parts.append(f"----- {log.name} (last {TAIL_LINES} lines)")
            parts.extend(lines[-TAIL_LINES:])
        return "\n".join(parts)


def children(pid: int, name: str = "dbus-daemon") -> list[int]:
    """Process ids of ``pid``'s children called ``name``."""
    return sorted(pids(name, parent=pid))


def running(name: str = "dbus-daemon") -> set[int]:
    """Process ids of every process called ``name``."""
    return pids(name)


def _kill_pid(pid: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)


@pytest.fixture
def procs(tmp_path: Path) -> Iterator[Processes]:
    """The test's processes; all are stopped at the end, and their output tails printed."""
    require_binary("dbus-daemon")
    processes = Processes(tmp_path / "logs")
    try:
        yield processes
    finally:
        processes.stop_all()
        print(processes.report())


def wait_for(
    condition: Callable[[], Any],
    timeout: float,
    what: str,
    procs: Processes,
    alive: tuple[str, ...] = (),
) -> Any:
    """Poll ``condition`` until it is truthy (returned); fail with the logs on timeout or when a
    process of ``alive`` exits meanwhile."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        for name in alive:
            if not procs.alive(name):
                code = procs.running[name].returncode
                pytest.fail(f"{name} exited ({code}) while waiting for {what}\n{procs.report()}")
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what}\n{procs.report()}")
        time.sleep(POLL)


def free_port() -> int:
    """A TCP port free now on the loopback interface."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def read_rows(run: Path) -> list[dict[str, str]]:
    """The complete rows of evaluations.csv (a row being written is left out)."""
    path = run / "evaluations.csv"
    if not path.exists():
        return []
    with open(path, newline="", encoding="utf-8") as file:
        return [row for row in csv.DictReader(file) if None not in row.values()]


def master_log(run: Path) -> str:
    """The run's master.log ('' before it exists)."""
    path = run / "master.log"
    return path.read_text(errors="replace") if path.exists() else ""


# --------------------------------------------------------------------------- the lab


@dataclass
class Lab:
    """A running ``surprise-sim-robots`` and what the master and the agents need."""

    procs: Processes
    robots_dir: Path
    info: dict[str, Any]
    master_config: Path
    run: Path

    def agent_config(self, index: int) -> Path:
        """The configuration surprise-sim-robots wrote for robot ``index``."""
        return Path(self.info["robots"][index]["config"])

    def start_agent(self, index: int) -> None:
        """Start robot ``index``'s agent as process ``agent-<index>``."""
        self.procs.start(
            f"agent-{index}", "robot_agent.cli", "--config", str(self.agent_config(index))
        )

    def start_master(self, *args: str) -> None:
        """Start ``surprise-master args`` as process ``master``."""
        self.procs.start("master", "master_service", *args)

    def stop_agents_and_server(self) -> None:
        """SIGTERM the agents and then the server: each exits 0, no dbus-daemon is left."""
        daemons = children(self.info["pid"])
        assert len(daemons) == ROBOTS, self.procs.report()
        for index in range(ROBOTS):
            self.procs.kill(f"agent-{index}", signal.SIGTERM)
        for index in range(ROBOTS):
            assert self.procs.wait(f"agent-{index}", STOP_TIMEOUT) == 0, self.procs.report()
        self.procs.kill("sim", signal.SIGTERM)
        assert self.procs.wait("sim", STOP_TIMEOUT) == 0, self.procs.report()
        assert not running() & set(daemons), "dbus-daemons left behind"
        assert not (self.robots_dir / "robots.json").exists()


def start_server(
    procs: Processes, robots_dir: Path, port: int, secret: Path, robots: int, *extra: str
) -> dict[str, Any]:
    """Start ``surprise-sim-robots`` as process ``sim``; its robots.json once it serves."""
    procs.start(
        "sim",
        "standins.serve",
        *("--scenario", "basic", "--robots", str(robots), "--seed", "5"),
        *("--dir", str(robots_dir), "--master-port", str(port), "--secret-file", str(secret)),
        *extra,
    )
    announced = robots_dir / "robots.json"
    wait_for(announced.exists, START_TIMEOUT, "robots.json", procs, alive=("sim",))
    return json.loads(announced.read_text())


@pytest.fixture
def lab(procs: Processes, tmp_path: Path) -> Lab:
    """surprise-sim-robots serving 4 robots, the master's configuration for a short run."""
    port = free_port()
    secret = tmp_path / "secret.key"
    secret.write_text(SECRET)
    robots_dir = tmp_path / "robots"
    # Short reconnection delays: the agents find a restarted master within a second.
    reconnect = ("--reconnect-initial", "0.1", "--reconnect-max", "1.0")
    info = start_server(procs, robots_dir, port, secret, ROBOTS, *reconnect)
    config = {
        "experiment": {
            "scenario": "basic",
            "robots": ROBOTS,
            "seed": 5,
            "evaluation_steps": STEPS,
            "post_evaluation_steps": STEPS,
            "evolution": {"evaluations": EVALUATIONS},
        },
        "host": "127.0.0.1",
        "port": port,
        "secret_file": str(secret),
        "allowed_robots": [robot["robot_id"] for robot in info["robots"]],
        # A round's deadline is 1 s + this: room for a slow agent on a loaded machine.
        "round_margin": 3.0,
        # A link is dead after 3 silent intervals: a killed process closes its socket at once
        # anyway, and 3 s tolerates a process stalled by a loaded machine.
        "heartbeat_interval": 1.0,
        "handshake_timeout": 5.0,
    }
    master_config = tmp_path / "master.yaml"
    master_config.write_text(yaml.safe_dump(config))
    return Lab(procs, robots_dir, info, master_config, tmp_path / "run")


def assert_complete(lab: Lab) -> list[dict[str, str]]:
    """The run is done: evaluations 1..E once each, the post-evaluation of every robot."""
    rows = read_rows(lab.run)
    report = lab.procs.report()
    assert [int(r["evaluation"]) for r in rows] == list(range(1, EVALUATIONS + 1)), report
    checkpoint = json.loads((lab.run / "checkpoint.json").read_text())
    assert checkpoint["phase"] == "done" and checkpoint["csv_rows"] == EVALUATIONS
    post = json.loads((lab.run / "post_evaluation.json").read_text())
    assert sorted(post["robots"]) == [f"sim-{i}" for i in range(ROBOTS)]
    assert all((lab.run / "traces" / f"sim-{i}.npz").exists() for i in range(ROBOTS))
    return rows


# --------------------------------------------------------------------------- tests


@pytest.mark.slow
def test_the_server_serves_each_robot_on_its_own_bus_until_sigterm(
    procs: Processes, tmp_path: Path
):
    robots_dir = tmp_path / "robots"
    robots_dir.mkdir()
    # An earlier server's configuration goes; a file of the person's own stays.
    (robots_dir / "agent-sim-7.yaml").write_text("# Written by surprise-sim-robots (pid 1)\n")
    (robots_dir / "agent-mine.yaml").write_text("robot_id: mine\n")
    reconnect = ("--reconnect-initial", "0.2", "--reconnect-max", "2")
    # Named as a lab's robots (the README's rehearsal names thymio-1 ...).
    ids = ("--ids", "thymio-1,thymio-2")
    info = start_server(
        procs, robots_dir, 7474, tmp_path / "absent.key", 2, "--poses", *ids, *reconnect
    )
    assert info["pid"] == procs.pid("sim")
    daemons = children(info["pid"])
    assert len(daemons) == 2
    buses = [robot["bus"] for robot in info["robots"]]
    assert len(set(buses)) == 2
    assert sorted(p.name for p in robots_dir.glob("agent-*.yaml")) == [
        "agent-mine.yaml",
        "agent-thymio-1.yaml",
        "agent-thymio-2.yaml",
    ]
    for index, robot in enumerate(info["robots"]):
        config = load_agent_config(robot["config"])
        assert config.robot_id == robot["robot_id"] == f"thymio-{index + 1}"
        assert robot["config"].endswith(f"agent-thymio-{index + 1}.yaml")
        assert config.body.thymio.bus == robot["bus"]
        assert config.master.port == 7474 and config.safety.profile == "stop"
        assert (config.reconnect.initial, config.reconnect.max) == (0.2, 2.0)

    async def drive_robot_0() -> list[float]:
        # The real driver, from another process: reads follow the 10 Hz steps; 1 s at half speed.
        base = ThymioBase(ThymioConfig(bus=buses[0]))
        await base.open()
        try:
            start, times = time.monotonic(), []
            await base.set_speeds(0.5, 0.5)
            for _ in range(10):
                await base.read()
                times.append(time.monotonic() - start)
        finally:
            await base.close()
        return times

    times = asyncio.run(drive_robot_0())
    # Ten reads wait for ten steps: about a second, not the milliseconds of ten plain calls.
    assert times[-1] > 0.8, times
    procs.kill("sim", signal.SIGTERM)
    assert procs.wait("sim", STOP_TIMEOUT) == 0, procs.report()
    assert not running() & set(daemons), "dbus-daemons left behind"
    assert not (robots_dir / "robots.json").exists()
    poses = np.load(robots_dir / "poses.npy")
    moved = np.linalg.norm(poses[-1, :, :2] - poses[0, :, :2], axis=1)
    # Half speed is 6.3 cm/s; the drive lasted about one second.
    assert 0.04 < moved[0] < 0.1 and moved[1] == 0.0, moved


@pytest.mark.slow
def test_an_agent_killed_and_restarted_during_the_run(lab: Lab):
    procs = lab.procs
    lab.start_master("run", "--config", str(lab.master_config), "--out", str(lab.run))
    for index in range(ROBOTS):
        lab.start_agent(index)
    wait_for(
        lambda: len(read_rows(lab.run)) >= ROWS_BEFORE_FAULT,
        RUN_TIMEOUT,
        f"{ROWS_BEFORE_FAULT} evaluations",
        procs,
        alive=("master", "sim"),
    )
    procs.kill("agent-1")  # SIGKILL: no Bye, the motors keep their last targets
    left = re.compile(r"robot sim-1 \(.*\) left")
    wait_for(
        lambda: left.search(master_log(lab.run)),
        START_TIMEOUT,
        "the master to see sim-1 leave",
        procs,
        alive=("master",),
    )
    lab.start_agent(1)
    assert procs.wait("master", RUN_TIMEOUT) == 0, procs.report()

    rows = assert_complete(lab)
    log = master_log(lab.run)
    leave = left.search(log)
    assert leave is not None
    after = log[leave.end() :]
    # What really happened: the run paused (the round in flight did not count, or the next one
    # waited for the robot), sim-1 joined again and later evaluations were counted.
    paused = any(int(r["attempts"]) > 1 for r in rows) or "waiting for robots" in after
    assert paused, log
    rejoined = re.search(r"robot sim-1 joined", after)
    assert rejoined is not None, log
    assert re.search(rf"evaluation \d+/{EVALUATIONS} ", after[rejoined.end() :]), log
    lab.stop_agents_and_server()


@pytest.mark.slow
def test_the_master_killed_and_resumed(lab: Lab):
    procs = lab.procs
    lab.start_master("run", "--config", str(lab.master_config), "--out", str(lab.run))
    for index in range(ROBOTS):
        lab.start_agent(index)
    wait_for(
        lambda: len(read_rows(lab.run)) >= ROWS_BEFORE_FAULT,
        RUN_TIMEOUT,
        f"{ROWS_BEFORE_FAULT} evaluations",
        procs,
        alive=("master", "sim"),
    )
    procs.kill("master")  # SIGKILL: no Bye, no last commit
    before = read_rows(lab.run)
    agent_pids = [procs.pid(f"agent-{i}") for i in range(ROBOTS)]

    lab.start_master("resume", str(lab.run))
    assert procs.wait("master", RUN_TIMEOUT) == 0, procs.report()

    rows = assert_complete(lab)
    # The rows the checkpoint counted stay as they were; only the last row written before the
    # kill may have been done again (its checkpoint may not have reached the disk).
    assert rows[: len(before) - 1] == before[:-1]
    log = master_log(lab.run)
    assert "resumed run" in log, log
    # The agents reconnected by themselves: the same processes, each welcomed twice.
    for index in range(ROBOTS):
        assert procs.pid(f"agent-{index}") == agent_pids[index] and procs.alive(f"agent-{index}")
        output = (procs.directory / f"agent-{index}.0.log").read_text()
        assert output.count("welcomed into run") >= 2, procs.report()
    lab.stop_agents_and_server()
