"""The real Aseba stack for tests: Aseba Playground's simulated Thymios behind Debian's own
``asebamedulla``, each medulla on its own private D-Bus.

The pieces are the product's, :mod:`standins.playground` (``surprise-sim-robots --backend
playground``), re-exported here under the names the tests use:

- :class:`Playground` runs ``asebaplayground`` headless (``QT_QPA_PLATFORM=offscreen``) with one
  Thymio II per port, in the lab's arena; killing it makes every robot vanish, as a switched-off
  Thymio does.
- :class:`Medulla` runs ``asebamedulla -p PORT "tcp:localhost;ROBOT_PORT"`` on one bus and, like
  systemd's ``Restart=always`` in deploy/systemd/asebamedulla.service, starts a fresh process
  :data:`RESTART_DELAY` seconds after one ended (whoever ended it).
- :class:`Bus` is a private ``dbus-daemon``.

What only tests need is here: :class:`Observer` reads a robot's variables through whichever
medulla runs, as a person with ``asebacmd`` would (what the motors are told, whatever the agent
believes), and a private /tmp for a command (:func:`private_tmp_command`).

The buses listen on abstract sockets, so processes with a private /tmp reach them too.
"""

from __future__ import annotations

import asyncio
import contextlib
import shutil
import subprocess
import sys
import time
from pathlib import Path

from needs import missing
from standins.playground import (
    RESTART_DELAY,
    START_TIMEOUT,
    STOP_TIMEOUT,
    Bus,
    Medulla,
    Playground,
    free_port,
)

__all__ = [
    "RESTART_DELAY",
    "START_TIMEOUT",
    "STOP_TIMEOUT",
    "Bus",
    "Medulla",
    "Observer",
    "Playground",
    "free_port",
    "have_private_tmp",
    "kept_in_tmp",
    "private_tmp_command",
    "require_aseba",
]

_TESTS = Path(__file__).resolve().parent.parent
if str(_TESTS / "agent") not in sys.path:
    sys.path.insert(0, str(_TESTS / "agent"))


def require_aseba() -> None:
    """Skip unless Debian's ``aseba`` is installed, except in CI, where it must be."""
    from needs import require_binary

    require_binary("asebamedulla")
    require_binary("asebaplayground")


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
