"""Aseba Playground's simulated Thymios behind Debian's real ``asebamedulla``, one private D-Bus
per robot: a lab day rehearsed without robots (``surprise-sim-robots --backend playground``,
docs/rehearsal.md).

- :class:`Arena` is the lab's arena in Playground's world: the carpet (a ground texture the
  Thymio's ground sensors read as the lab's carpet, bright between carpet and walls), four walls
  and the robots' start poses, placed as :class:`~simulator.world.World` places them.
- :class:`Bus` is a private ``dbus-daemon`` on an abstract socket (processes with a private /tmp
  reach it too).
- :class:`Playground` runs ``asebaplayground`` headless (``QT_QPA_PLATFORM=offscreen``) with one
  Thymio II per TCP port; killing it makes every robot vanish, as a switched-off Thymio does.
- :class:`Medulla` runs ``asebamedulla -p PORT "tcp:localhost;ROBOT_PORT"`` on one bus and, like
  systemd's ``Restart=always`` in deploy/systemd/asebamedulla.service, starts a fresh process
  :data:`RESTART_DELAY` seconds after one ended, whoever ended it (an agent with
  ``body.thymio.restart_medulla`` ends a medulla that lost its robot).
- :class:`PlaygroundLab` starts all of it for N robots and stops every process it started.

Every process started here gets SIGTERM when this one dies, even by SIGKILL (Linux's
``PR_SET_PDEATHSIG``), so no Playground, medulla or dbus-daemon outlives its server.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Final

from drivers.config import PROGRAM_NODE
from drivers.thymio import ASEBA_INTERFACE, ASEBA_PATH, ASEBA_SERVICE
from simulator.scenarios import WorldConfig
from standins.playground_world import Arena

__all__ = [
    "ENKI_UNIT_SPEED",
    "PLAYGROUND_SPEED_SCALE",
    "PLAYGROUND_UNIT_SPEED",
    "PROGRAMS",
    "RESTART_DELAY",
    "START_TIMEOUT",
    "STOP_TIMEOUT",
    "Arena",
    "Bus",
    "Medulla",
    "Playground",
    "PlaygroundLab",
    "free_port",
    "nodes_listed",
    "speed_scale_for",
]

log = logging.getLogger("standins.playground")

#: Seconds for a program to be ready (Playground listening, medulla listing its robot); Playground
#: starts in about a second, Qt and Enki on a loaded two-core machine in several.
START_TIMEOUT: Final = 20.0
#: Seconds between the end of a medulla and its successor: systemd's RestartSec=2 in the unit,
#: shortened so that an agent that ended a medulla has a fresh one soon (it retries for longer).
RESTART_DELAY: Final = 0.5
#: Seconds a process gets to exit after SIGTERM before it is killed: Playground, medulla and
#: dbus-daemon exit within milliseconds; this bounds a hung one.
STOP_TIMEOUT: Final = 5.0
#: Seconds a fresh medulla gets to list its robot. One that connected while Playground was still
#: starting may never list it (it asks for the node's description once): it is restarted.
LIST_TIMEOUT: Final = 5.0
#: Medullas started per robot before giving up on listing it.
LIST_ATTEMPTS: Final = 4
#: Seconds between two looks at a process or a bus (supervision, readiness).
POLL: Final = 0.05
#: Seconds one D-Bus call of a readiness check may take (a medulla without its robot never
#: answers ``GetVariable``, but ``GetNodesList`` answers at once).
CALL_TIMEOUT: Final = 1.0

#: Enki's Thymio II drives 16.6 cm/s at the motor target 500 (``Thymio2.cpp``:
#: ``target * 16.6 / 500``, with 2.7 % wheel noise), in Playground's simulated time.
ENKI_UNIT_SPEED: Final = 0.166 / 500
#: The Playground Thymio's wheel speed per motor unit in m/s of wall-clock time, measured from its
#: pose (Playground's D-Bus) at the targets 160, 319 and 500: 0.0326-0.0329 cm/s, 1.5 % below
#: Enki's, because Playground's clock runs 1.1 % slow (it steps a fixed time per Qt timer tick,
#: and the ticks come late; a loaded machine slows it further). The agents run on wall-clock
#: time. A real Thymio's unit is about 0.04 cm/s.
PLAYGROUND_UNIT_SPEED: Final = 0.000327
#: What ``body.thymio.speed_scale`` makes a Playground Thymio drive the lab's 10.6 cm/s
#: (``simulation.max_speed``) at full speed: 324.2 units, where a real Thymio needs 265.
PLAYGROUND_SPEED_SCALE: Final = round(WorldConfig().max_speed / PLAYGROUND_UNIT_SPEED, 1)

#: The node name of a Playground Thymio, as of a real one.
NODE: Final = PROGRAM_NODE
#: The programs this module runs, all from Debian's ``aseba`` package but the daemon.
PROGRAMS: Final = ("asebaplayground", "asebamedulla", "dbus-daemon")


def free_port() -> int:
    """A TCP port free now on the loopback interface."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def speed_scale_for(max_speed: float) -> float:
    """The ``speed_scale`` that makes a Playground Thymio drive ``max_speed`` m/s at 1.0."""
    return round(max_speed / PLAYGROUND_UNIT_SPEED, 1)


def _die_with_parent() -> None:
    # Runs in the child before exec: a SIGKILLed server skips its clean-up, and nothing it
    # started may outlive it. PR_SET_PDEATHSIG (1) is Linux's; elsewhere a child may linger.
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)


def _spawn(
    argv: list[str],
    out: IO[bytes] | int,
    env: dict[str, str] | None = None,
    cwd: Path | None = None,
) -> subprocess.Popen[bytes]:
    """Start ``argv`` with its output (and errors) to ``out``, or its output piped and its errors
    dropped when ``out`` is ``subprocess.PIPE``.

    Call it from the event loop's thread only: the death signal follows the thread that started
    the child, and a worker thread of ``asyncio.to_thread`` ends long before the server."""
    piped = out == subprocess.PIPE
    return subprocess.Popen(
        argv,
        stdin=subprocess.DEVNULL,
        stdout=out,
        stderr=subprocess.DEVNULL if piped else subprocess.STDOUT,
        env=env,
        cwd=cwd,
        preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
    )


def end_process(process: subprocess.Popen[bytes] | None, timeout: float = STOP_TIMEOUT) -> None:
    """End ``process`` if it still runs: SIGTERM, then SIGKILL after ``timeout`` seconds."""
    if process is None or process.poll() is not None:
        return
    process.terminate()
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


async def _wait_until(condition: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout} s waiting for {what}")
        await asyncio.sleep(POLL)


def listening(port: int) -> bool:
    """Whether something listens on TCP ``port``, from the kernel's table: a Playground robot
    serves one connection, and a probe that connects and hangs up can leave it refusing the next
    one (medulla's)."""
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with contextlib.suppress(OSError), open(table) as file:
            for line in file.readlines()[1:]:
                fields = line.split()
                if fields[3] == "0A" and int(fields[1].rsplit(":", 1)[1], 16) == port:
                    return True
    return False


# --------------------------------------------------------------------------- the world


# --------------------------------------------------------------------------- the processes


class Bus:
    """A private ``dbus-daemon`` on an abstract socket."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.address = ""
        self._process: subprocess.Popen[bytes] | None = None

    @property
    def pid(self) -> int | None:
        """The daemon's process id while it runs."""
        process = self._process
        return process.pid if process is not None and process.poll() is None else None

    def start(self) -> str:
        """Start the daemon; its address."""
        from standins.fake_medulla import bus_config

        self.directory.mkdir(parents=True, exist_ok=True)
        config = self.directory / "bus.conf"
        name = f"minimize-surprise-{os.getpid()}-{id(self)}"
        config.write_text(bus_config(f"unix:abstract={name}"), encoding="utf-8")
        self._process = _spawn(
            ["dbus-daemon", f"--config-file={config}", "--print-address", "--nofork"],
            subprocess.PIPE,
        )
        assert self._process.stdout is not None
        self.address = self._process.stdout.readline().decode().strip()
        if not self.address:
            raise RuntimeError("dbus-daemon did not start")
        return self.address

    def stop(self) -> None:
        """End the daemon."""
        end_process(self._process)


class Playground:
    """``asebaplayground`` with one Thymio II per port in ``ports``, headless, in ``arena`` (by
    default the lab's, :func:`Arena.of` the ``basic`` scenario with seed 0). With ``bus`` it
    offers its world on that D-Bus (``ch.epfl.mobots.AsebaPlayground``: the robots' poses)."""

    def __init__(
        self, directory: Path, ports: list[int], arena: Arena | None = None, bus: str = ""
    ) -> None:
        self.directory = directory
        self.ports = ports
        if arena is None:
            from simulator.scenarios import scenario_config

            arena = Arena.of(scenario_config("basic", {"robots": len(ports)}), 0)
        self.arena = arena
        self.bus = bus
        self.starts = 0
        self._process: subprocess.Popen[bytes] | None = None

    @property
    def pid(self) -> int | None:
        """Playground's process id while it runs."""
        process = self._process
        return process.pid if process is not None and process.poll() is None else None

    @property
    def world(self) -> Path:
        """The world file."""
        return self.directory / "world.playground"

    def _env(self) -> dict[str, str]:
        # Its settings, the robots' SD card files and Qt's runtime files stay in the directory
        # rather than in the user's home.
        xdg = self.directory / "xdg"
        runtime = xdg / "runtime"
        runtime.mkdir(parents=True, exist_ok=True)
        runtime.chmod(0o700)  # Qt refuses a runtime directory others may enter
        env = {
            **os.environ,
            "QT_QPA_PLATFORM": "offscreen",
            "XDG_RUNTIME_DIR": str(runtime),
            "XDG_CONFIG_HOME": str(xdg / "config"),
            "XDG_DATA_HOME": str(xdg / "data"),
            "XDG_CACHE_HOME": str(xdg / "cache"),
        }
        if self.bus:
            env["DBUS_SESSION_BUS_ADDRESS"] = self.bus
        return env

    async def start(self) -> None:
        """Start it and wait until every robot listens."""
        self.directory.mkdir(parents=True, exist_ok=True)
        (self.directory / "ground.png").write_bytes(self.arena.ground_png())
        self.world.write_text(self.arena.world_xml(self.ports, "ground.png"), encoding="utf-8")
        env = self._env()
        with open(self.directory / f"playground.{self.starts}.log", "wb") as out:
            self._process = _spawn(
                ["asebaplayground", str(self.world)], out, env=env, cwd=self.directory
            )
        self.starts += 1
        process = self._process

        def ready() -> bool:
            if process.poll() is not None:
                raise RuntimeError(f"asebaplayground exited ({process.returncode}); see its log")
            return all(listening(p) for p in self.ports)

        await _wait_until(ready, START_TIMEOUT, "Aseba Playground")

    def ended(self) -> int | None:
        """Its exit code once it has ended, else None."""
        return None if self._process is None else self._process.poll()

    def kill(self) -> None:
        """SIGKILL: every robot vanishes at once, as when it is switched off."""
        if self._process is not None and self._process.poll() is None:
            self._process.kill()
            self._process.wait()

    def stop(self) -> None:
        """End it."""
        end_process(self._process)


class Medulla:
    """One robot's ``asebamedulla`` on one bus, restarted whenever it ends (see the module).

    Its own Aseba TCP port (``-p``, for Aseba Studio) is :attr:`port`; each start's output goes
    to ``directory/medulla.<n>.log``."""

    def __init__(
        self, directory: Path, bus: str, robot_port: int, env: dict[str, str] | None = None
    ) -> None:
        self.directory = directory
        self.bus = bus
        self.env = env or {}
        self.robot_port = robot_port
        self.port = free_port()
        self.starts = 0
        self._process: subprocess.Popen[bytes] | None = None
        self._supervisor: asyncio.Task[None] | None = None

    @property
    def pid(self) -> int | None:
        """The running medulla's process id."""
        process = self._process
        return process.pid if process is not None and process.poll() is None else None

    def _spawn(self) -> None:
        env = {**os.environ, **self.env, "DBUS_SESSION_BUS_ADDRESS": self.bus}
        self.directory.mkdir(parents=True, exist_ok=True)
        argv = ["asebamedulla", "-v", "-p", str(self.port), f"tcp:localhost;{self.robot_port}"]
        with open(self.directory / f"medulla.{self.starts}.log", "wb") as out:
            self._process = _spawn(argv, out, env=env)
        self.starts += 1

    async def start(self) -> None:
        """Start it, and keep restarting it until :meth:`stop`."""
        self._spawn()
        self._supervisor = asyncio.create_task(self._supervise())

    async def _supervise(self) -> None:
        while True:
            await asyncio.sleep(POLL)
            if self._process is not None and self._process.poll() is not None:
                await asyncio.sleep(RESTART_DELAY)
                self._spawn()

    def end(self, signum: int = signal.SIGTERM) -> int | None:
        """Send ``signum`` to the running medulla (its supervisor starts another); its pid."""
        pid = self.pid
        if pid is not None:
            os.kill(pid, signum)
        return pid

    async def stop(self) -> None:
        """End it for good."""
        if self._supervisor is not None:
            self._supervisor.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._supervisor
        end_process(self._process)


async def nodes_listed(bus: str, node: str = NODE, timeout: float = LIST_TIMEOUT) -> bool:
    """Whether a medulla on ``bus`` lists ``node`` within ``timeout`` seconds."""
    from dbus_fast import Message, MessageType
    from dbus_fast.aio import MessageBus

    deadline = time.monotonic() + timeout
    connection = await MessageBus(bus_address=bus).connect()
    try:
        while time.monotonic() < deadline:
            message = Message(
                destination=ASEBA_SERVICE,
                path=ASEBA_PATH,
                interface=ASEBA_INTERFACE,
                member="GetNodesList",
            )
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(CALL_TIMEOUT):
                    answer = await connection.call(message)
                if answer.message_type == MessageType.METHOD_RETURN and node in answer.body[0]:
                    return True
            await asyncio.sleep(0.1)
        return False
    finally:
        connection.disconnect()


# --------------------------------------------------------------------------- the lab


@dataclass
class PlaygroundRobot:
    """One Playground Thymio with its own bus and (supervised) medulla."""

    index: int
    robot_port: int
    bus: Bus
    medulla: Medulla


@dataclass
class PlaygroundLab:
    """Playground with the robots of ``arena``, each behind its own medulla on its own bus,
    every process started on entering and ended on leaving (an async context manager). Its
    files are in ``directory``: the world, the ground texture and every process's log."""

    directory: Path
    arena: Arena
    robots: list[PlaygroundRobot] = field(default_factory=list)
    world_bus: Bus | None = None
    playground: Playground | None = None

    async def __aenter__(self) -> PlaygroundLab:
        try:
            await self._start()
        except BaseException:
            await self.close()
            raise
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _start(self) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        for stale in self.directory.glob("**/*.log"):  # an earlier server's
            stale.unlink()
        self.world_bus = Bus(self.directory / "world-bus")
        self.world_bus.start()
        ports = [free_port() for _ in self.arena.poses]
        self.playground = Playground(self.directory, ports, self.arena, self.world_bus.address)
        await self.playground.start()
        for index, port in enumerate(ports):
            bus = Bus(self.directory / f"robot-{index}" / "bus")
            bus.start()
            medulla = Medulla(self.directory / f"robot-{index}", bus.address, port)
            self.robots.append(PlaygroundRobot(index, port, bus, medulla))
            await medulla.start()
        await asyncio.gather(*(self._listed(robot) for robot in self.robots))

    async def _listed(self, robot: PlaygroundRobot) -> None:
        for _ in range(LIST_ATTEMPTS):
            if await nodes_listed(robot.bus.address):
                return
            log.info("medulla of robot %d does not list it: starting another", robot.index)
            robot.medulla.end()
        raise RuntimeError(
            f"no medulla listed robot {robot.index} in {LIST_ATTEMPTS} starts; see the logs in "
            f"{robot.medulla.directory}"
        )

    async def watch(self) -> int:
        """Wait until Playground ends by itself (a crash: every robot is gone); its exit code."""
        assert self.playground is not None
        while (code := self.playground.ended()) is None:
            await asyncio.sleep(POLL * 10)
        return code

    async def close(self) -> None:
        """End every process: the medullas first, which hold the robots, Playground last."""
        for robot in self.robots:
            await robot.medulla.stop()
            robot.bus.stop()
        if self.playground is not None:
            self.playground.stop()
        if self.world_bus is not None:
            self.world_bus.stop()
