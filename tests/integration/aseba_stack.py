"""The real Aseba stack for tests: Aseba Playground's simulated Thymios behind Debian's own
``asebamedulla``, each medulla on its own private D-Bus.

- :class:`Playground` runs ``asebaplayground`` headless (``QT_QPA_PLATFORM=offscreen``) with one
  Thymio II per port; killing it makes every robot vanish, as a switched-off Thymio does.
- :class:`Medulla` runs ``asebamedulla -p PORT "tcp:localhost;ROBOT_PORT"`` on one bus and, like
  systemd's ``Restart=always`` in deploy/systemd/asebamedulla.service, starts a fresh process
  :data:`RESTART_DELAY` seconds after one ended (whoever ended it).
- :class:`Observer` reads a robot's variables through whichever medulla runs, as a person with
  ``asebacmd`` would: what the motors are told, whatever the agent believes.

The buses listen on abstract sockets, so processes with a private /tmp reach them too.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Final

from needs import end_process, missing
from sim_stub.fake_medulla import bus_config

_TESTS = Path(__file__).resolve().parent.parent
if str(_TESTS / "agent") not in sys.path:
    sys.path.insert(0, str(_TESTS / "agent"))

#: Seconds for a program to be ready (Playground listening, medulla owning its name).
START_TIMEOUT: Final = 20.0
#: Seconds between the end of a medulla and its successor: systemd's RestartSec=2 in the unit,
#: shortened so that the tests stay quick.
RESTART_DELAY: Final = 0.5
#: Seconds a process gets to exit after SIGTERM before it is killed.
STOP_TIMEOUT: Final = 5.0

_WORLD = """<!DOCTYPE aseba-playground>
<aseba-playground>
  <color name="wall" r="0.9" g="0.9" b="0.9" />
  <world w="{side}" h="{side}" color="wall"/>
{robots}
</aseba-playground>
"""
_ROBOT = '  <robot type="thymio2" x="{x}" y="{y}" port="{port}" angle="0" name="T{index}"/>'


def require_aseba() -> None:
    """Skip unless Debian's ``aseba`` is installed, except in CI, where it must be."""
    from needs import require_binary

    require_binary("asebamedulla")
    require_binary("asebaplayground")


def free_port() -> int:
    """A TCP port free now on the loopback interface."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


async def _wait_until(condition, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout} s waiting for {what}")
        await asyncio.sleep(0.05)


def _listening(port: int) -> bool:
    # Read the kernel's table rather than connect: a Playground robot serves one connection, and
    # a probe that connects and hangs up can leave it refusing the next one (medulla's).
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with contextlib.suppress(OSError), open(table) as file:
            for line in file.readlines()[1:]:
                fields = line.split()
                if fields[3] == "0A" and int(fields[1].rsplit(":", 1)[1], 16) == port:
                    return True
    return False


def _end(process: subprocess.Popen[bytes] | None) -> None:
    end_process(process, STOP_TIMEOUT)


class Bus:
    """A private ``dbus-daemon`` on an abstract socket."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.address = ""
        self._process: subprocess.Popen[bytes] | None = None

    def start(self) -> str:
        """Start the daemon; its address."""
        self.directory.mkdir(parents=True, exist_ok=True)
        config = self.directory / "bus.conf"
        name = f"minimize-surprise-test-{os.getpid()}-{id(self)}"
        config.write_text(bus_config(f"unix:abstract={name}"), encoding="utf-8")
        self._process = subprocess.Popen(
            ["dbus-daemon", f"--config-file={config}", "--print-address", "--nofork"],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            stdin=subprocess.DEVNULL,
        )
        assert self._process.stdout is not None
        self.address = self._process.stdout.readline().decode().strip()
        if not self.address:
            raise RuntimeError("dbus-daemon did not start")
        return self.address

    def stop(self) -> None:
        """End the daemon."""
        _end(self._process)


class Playground:
    """``asebaplayground`` with one Thymio II per port in ``ports``, headless."""

    def __init__(self, directory: Path, ports: list[int]) -> None:
        self.directory = directory
        self.ports = ports
        self._process: subprocess.Popen[bytes] | None = None
        self.starts = 0

    async def start(self) -> None:
        """Start it and wait until every robot listens."""
        self.directory.mkdir(parents=True, exist_ok=True)
        robots = "\n".join(
            _ROBOT.format(x=40 + 60 * i, y=60, port=port, index=i)
            for i, port in enumerate(self.ports)
        )
        world = self.directory / "world.playground"
        world.write_text(_WORLD.format(side=60 * len(self.ports) + 60, robots=robots))
        env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
        env.setdefault("XDG_RUNTIME_DIR", tempfile.mkdtemp(prefix="runtime-"))
        log = open(self.directory / f"playground.{self.starts}.log", "wb")  # noqa: SIM115
        self.starts += 1
        with log:
            self._process = subprocess.Popen(
                ["asebaplayground", str(world)],
                env=env,
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                cwd=self.directory,
            )
        await _wait_until(
            lambda: all(_listening(p) for p in self.ports), START_TIMEOUT, "Aseba Playground"
        )

    def kill(self) -> None:
        """SIGKILL: every robot vanishes at once, as when it is switched off."""
        if self._process is not None and self._process.poll() is None:
            self._process.kill()
            self._process.wait()

    def stop(self) -> None:
        """End it."""
        _end(self._process)


class Medulla:
    """One robot's ``asebamedulla`` on one bus, restarted whenever it ends (see the module)."""

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
        with open(self.directory / f"medulla.{self.starts}.log", "wb") as log:
            self._process = subprocess.Popen(
                ["asebamedulla", "-v", "-p", str(self.port), f"tcp:localhost;{self.robot_port}"],
                env=env,
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
            )
        self.starts += 1

    async def start(self) -> None:
        """Start it, and keep restarting it until :meth:`stop`."""
        self._spawn()
        self._supervisor = asyncio.create_task(self._supervise())

    async def _supervise(self) -> None:
        while True:
            await asyncio.sleep(0.05)
            if self._process is not None and self._process.poll() is not None:
                await asyncio.sleep(RESTART_DELAY)
                self._spawn()

    def end(self, signum: int = signal.SIGTERM) -> int | None:
        """Send ``signum`` to the running medulla (its service starts another); its pid."""
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
        _end(self._process)


class Observer:
    """Reads a robot's variables through whichever medulla owns the name now."""

    def __init__(self, bus: str, node: str = "thymio-II", timeout: float = 0.5) -> None:
        self.address = bus
        self.node = node
        self.timeout = timeout
        self._bus = None

    async def __aenter__(self) -> Observer:
        from dbus_fast.aio import MessageBus

        self._bus = await MessageBus(bus_address=self.address).connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._bus is not None:
            self._bus.disconnect()

    async def call(self, member: str, signature: str = "", body: tuple = ()) -> list:
        """Call ``member`` on medulla; raises ``RuntimeError`` for an error or no answer."""
        from dbus_fast import Message, MessageType

        message = Message(
            destination="ch.epfl.mobots.Aseba",
            path="/",
            interface="ch.epfl.mobots.AsebaNetwork",
            member=member,
            signature=signature,
            body=list(body),
        )
        try:
            async with asyncio.timeout(self.timeout):
                answer = await self._bus.call(message)
        except TimeoutError:
            raise RuntimeError(f"{member}{body}: no answer within {self.timeout} s") from None
        if answer.message_type == MessageType.ERROR:
            raise RuntimeError(f"{member}{body}: {answer.error_name}: {answer.body}")
        return answer.body

    async def get(self, variable: str) -> list[int]:
        """A variable's values, from the robot."""
        (values,) = await self.call("GetVariable", "ss", (self.node, variable))
        return list(values)

    async def targets(self) -> tuple[int, int]:
        """The motor targets the robot holds now."""
        left = await self.get("motor.left.target")
        right = await self.get("motor.right.target")
        return left[0], right[0]

    async def ready(self, timeout: float = START_TIMEOUT) -> None:
        """Wait until a medulla lists the node."""
        deadline = time.monotonic() + timeout
        while True:
            with contextlib.suppress(RuntimeError):
                (nodes,) = await self.call("GetNodesList")
                if self.node in nodes:
                    return
            if time.monotonic() > deadline:
                raise TimeoutError(f"no medulla listed {self.node} within {timeout} s")
            await asyncio.sleep(0.1)


def have_private_tmp() -> bool:
    """Whether this machine lets a process have its own /tmp (``unshare --mount``, root)."""
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(
        ["unshare", "--mount", "--propagation", "private", "--", "sh", "-c",
         "mount -t tmpfs none /tmp"],
        capture_output=True,
    )  # fmt: skip
    return probe.returncode == 0


def kept_in_tmp() -> list[Path]:
    """The entries of /tmp that this Python runs from: its venv, its interpreter, this checkout
    (a clone under /tmp is common); a private /tmp must still show them."""
    tmp = Path("/tmp").resolve()
    used = [Path(sys.prefix), Path(sys.base_prefix), Path(sys.executable), _TESTS.parent]
    used += [Path(entry) for entry in sys.path if entry]
    kept = set()
    for path in used:
        resolved = path.resolve()
        if resolved.is_relative_to(tmp) and resolved != tmp:
            kept.add(tmp / resolved.relative_to(tmp).parts[0])
    return sorted(p for p in kept if p.is_dir())


_PRIVATE_TMP_SCRIPT = """
set -e
private=$1; shift
while [ "$1" != -- ]; do
    mkdir -p "$private/$(basename "$1")"
    mount --bind "$1" "$private/$(basename "$1")"
    shift
done
shift
mount --rbind "$private" /tmp
exec "$@"
"""


def private_tmp_command(command: list[str], private: Path) -> list[str]:
    """``command`` with a /tmp of its own, as systemd's ``PrivateTmp=yes`` gives a unit: the empty
    directory ``private`` is its /tmp, so what it writes there is not in the /tmp that other
    processes see. The parts of the real /tmp this Python runs from (:func:`kept_in_tmp`) are
    mounted into it, so the command finds its interpreter and this checkout wherever they are."""
    if not have_private_tmp():
        missing(
            "a private /tmp needs unshare --mount, which needs root (apt-get install util-linux)"
        )
    private.mkdir(parents=True, exist_ok=True)
    kept = [str(p) for p in kept_in_tmp()]
    return [
        "unshare", "--mount", "--propagation", "private", "--",
        "sh", "-c", _PRIVATE_TMP_SCRIPT, "private-tmp", str(private), *kept, "--", *command,
    ]  # fmt: skip
