"""A fake asebamedulla on a private D-Bus, for testing :mod:`drivers.thymio` without a robot.

:func:`private_bus` starts a throw-away ``dbus-daemon`` and yields its address;
:func:`serve_fake_medulla` exports ``ch.epfl.mobots.AsebaNetwork`` at ``/`` under the name
``ch.epfl.mobots.Aseba`` on it, backed by a :class:`ThymioModel` (raw sensor values in, motor
targets out). The fake follows the real medulla (with Aseba Playground as the robot) where the
drivers can tell; docs/thymio.md lists what was observed:

- unknown nodes and variables are ``org.freedesktop.DBus.Error.InvalidArgs`` errors;
- ``GetVariable`` never answers while the robot is disconnected or the fake is in ``hang``
  mode (the calls are released with an error when the fake shuts down);
- ``IsConnected`` stays true for :data:`IS_CONNECTED_LAG` seconds after the robot went away;
- ``SetVariable`` of an unknown node or variable is recorded in :attr:`FakeMedulla.rejected` and
  answered with ``InvalidArgs``, which reaches only a caller that expects a reply (dbus-fast
  sends none to ``NO_REPLY_EXPECTED``, as the drivers set for the motors): silent for the
  motors' writes, told to the top LED's, as the real medulla does;
- ``LoadScripts`` answers a missing file or a malformed program with an error when the caller
  expects a reply (the real one aborts on malformed XML; it answers compile errors), resets the
  robot's VM (the program's variables start from their initial values) and makes the program's
  ``var`` variables known *to this medulla only*: a medulla started later does not know them,
  although the program keeps running on the robot (:class:`ThymioVM`, which outlives any one
  medulla and runs the failsafe program's timer).

This module imports ``dbus_fast`` at the top: it is a test double, not part of the drivers.
"""

import asyncio
import contextlib
import ctypes
import re
import shutil
import signal
import sys
import tempfile
import time
import weakref
import xml.etree.ElementTree as ET
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any, Protocol

from dbus_fast import RequestNameReply
from dbus_fast.aio import MessageBus
from dbus_fast.constants import ErrorType
from dbus_fast.errors import DBusError
from dbus_fast.service import ServiceInterface, dbus_method

from drivers.thymio import (
    ASEBA_INTERFACE,
    ASEBA_PATH,
    ASEBA_SERVICE,
    FAILSAFE_TICK,
    FWVERSION,
    HEARTBEAT,
    LEDS_TOP,
)

#: Seconds to wait for dbus-daemon to print its address, and for it to exit.
DAEMON_TIMEOUT = 10.0
#: Seconds the real medulla keeps answering ``IsConnected`` with true after the robot went away
#: (measured against Aseba Playground: 3.5 to 4.3 s).
IS_CONNECTED_LAG = 3.8
GROUND_VARIABLES = ("prox.ground.reflected", "prox.ground.delta", "prox.ground.ambiant")
MOTOR_TARGETS = {"motor.left.target": "left", "motor.right.target": "right"}
#: What Aseba Playground's Thymio answers for ``_fwversion`` (Debian's aseba, measured).
PLAYGROUND_FWVERSION = (11, 0)
_VAR_RE = re.compile(r"^\s*var\s+([A-Za-z_][\w.]*)\s*(?:\[\s*(\d+)\s*\])?\s*(?:=\s*(-?\d+))?", re.M)

_BUS_CONFIG = """<!DOCTYPE busconfig PUBLIC "-//freedesktop//DTD D-Bus Bus Configuration 1.0//EN"
 "http://www.freedesktop.org/standards/dbus/1.0/busconfig.dtd">
<busconfig>
  <type>session</type>
  <listen>{listen}</listen>
  <auth>EXTERNAL</auth>
  <policy context="default">
    <allow send_destination="*" eavesdrop="true"/>
    <allow eavesdrop="true"/>
    <allow own="*"/>
  </policy>
</busconfig>
"""


class ThymioModel(Protocol):
    """What the fake medulla serves: a robot's raw sensors and where its motor targets go.

    ``variables`` stores every other variable (written ones, the program's user variables).
    """

    variables: dict[str, list[int]]

    def prox_horizontal(self) -> list[int]:
        """The 7 raw horizontal IR values, 0..4500."""

    def ground(self, variable: str) -> list[int]:
        """The 2 raw values of a ground variable (``prox.ground.reflected`` ...), 0..1023."""

    def set_target(self, side: str, value: int) -> None:
        """A new motor target for ``side`` (``"left"`` or ``"right"``), in motor units."""


class StaticThymioModel:
    """A robot whose sensors read what the test sets and which records its motor targets."""

    def __init__(
        self,
        prox: list[int] | None = None,
        reflected: list[int] | None = None,
        delta: list[int] | None = None,
    ) -> None:
        self.prox = list(prox or [0] * 7)
        self.grounds: dict[str, list[int]] = {
            "prox.ground.reflected": list(reflected or [0, 0]),
            "prox.ground.delta": list(delta or [0, 0]),
            "prox.ground.ambiant": [0, 0],
        }
        self.targets: dict[str, int] = {"left": 0, "right": 0}
        #: Every target received, in order, as ``(side, value)``.
        self.target_log: list[tuple[str, int]] = []
        #: Every ``leds.top`` written, in order (three values 0..32).
        self.led_log: list[list[int]] = []
        #: The firmware's version as Playground's Thymio answers it; a test may change it.
        self.variables: dict[str, list[int]] = {FWVERSION: list(PLAYGROUND_FWVERSION)}

    def prox_horizontal(self) -> list[int]:
        """The values in :attr:`prox`."""
        return list(self.prox)

    def ground(self, variable: str) -> list[int]:
        """The values in :attr:`grounds` for ``variable``."""
        return list(self.grounds[variable])

    def set_target(self, side: str, value: int) -> None:
        """Record the target in :attr:`targets` and :attr:`target_log`."""
        self.targets[side] = value
        self.target_log.append((side, value))

    def set_top_led(self, values: list[int]) -> None:
        """Record a ``leds.top`` write in :attr:`led_log`."""
        self.led_log.append(list(values))


def _int16(values: list[int]) -> list[int]:
    return [max(-32768, min(32767, int(v))) for v in values]


def _declared(code: str) -> dict[str, list[int]]:
    """The ``var`` declarations of an Aseba program with their initial values."""
    return {
        name: [int(initial or 0)] * int(size or 1) for name, size, initial in _VAR_RE.findall(code)
    }


class ThymioVM:
    """The robot's Aseba VM, as far as this project's programs need it.

    It belongs to the robot, not to medulla: a program keeps running, with its variables, when
    the medulla that loaded it ends. :meth:`load` resets the VM with a new program (its variables
    start from their initial values). A program with a ``heartbeat`` variable and a ``timer0``
    handler is run as the failsafe program (drivers/failsafe.aesl): every tick the heartbeat
    counts down, and at 0 both motor targets are held at 0.
    """

    def __init__(self, model: ThymioModel) -> None:
        self.model = model
        #: The code of the running program, or None.
        self.program: str | None = None
        #: Ticks of the failsafe timer so far.
        self.ticks = 0
        self._timer: asyncio.Task[None] | None = None

    def load(self, code: str) -> dict[str, list[int]]:
        """Reset the VM with ``code``; returns the program's variables with their values."""
        declared = _declared(code)
        for name in _declared(self.program or ""):
            self.model.variables.pop(name, None)
        self.model.variables.update({k: list(v) for k, v in declared.items()})
        self.program = code
        failsafe = HEARTBEAT in declared and "onevent timer0" in code
        if failsafe and self._timer is None:
            self._timer = asyncio.get_running_loop().create_task(self._run_timer())
        elif not failsafe:
            self.close()
        return declared

    def close(self) -> None:
        """Stop the program's timer (the robot was switched off, or the test ends)."""
        timer, self._timer = self._timer, None
        if timer is not None:
            timer.cancel()

    async def _run_timer(self) -> None:
        while True:
            await asyncio.sleep(FAILSAFE_TICK)
            self.ticks += 1
            variables = self.model.variables
            beat = variables.get(HEARTBEAT, [0])[0]
            if beat > 0:
                beat -= 1
                variables[HEARTBEAT] = [beat]
            if beat == 0:
                for variable, side in MOTOR_TARGETS.items():
                    if model_target(self.model, variable) != 0:
                        variables[variable] = [0]
                        self.model.set_target(side, 0)


def model_target(model: ThymioModel, variable: str) -> int:
    """The motor target ``variable`` of ``model`` now (its ``targets`` if it keeps them)."""
    targets = getattr(model, "targets", None)
    if isinstance(targets, dict):
        return int(targets.get(MOTOR_TARGETS[variable], 0))
    return int(model.variables.get(variable, [0])[0])


#: The VM of each robot model, shared by every medulla serving that model.
_VMS: weakref.WeakKeyDictionary[Any, ThymioVM] = weakref.WeakKeyDictionary()


def vm_of(model: ThymioModel) -> ThymioVM:
    """The :class:`ThymioVM` of ``model`` (created on first use, shared by its medullas)."""
    vm = _VMS.get(model)
    if vm is None:
        vm = _VMS[model] = ThymioVM(model)
    return vm


class FakeMedulla:
    """The fake's state: the model, fault switches and what clients did.

    Switches: :attr:`hang` (``GetVariable`` never answers), :meth:`disconnect_robot` (the robot
    went away: reads hang, writes are dropped, ``IsConnected`` turns false after
    :attr:`connected_lag` seconds), :attr:`errors` (variable name -> error text returned by
    ``GetVariable``), :attr:`latency` (seconds before ``GetVariable`` answers). Records:
    :attr:`calls`, :attr:`rejected`, :attr:`program`, :attr:`loaded_scripts`,
    :attr:`max_in_flight` (most ``GetVariable`` calls pending at once).
    """

    def __init__(self, model: ThymioModel, node: str = "thymio-II") -> None:
        self.model = model
        self.node = node
        self.vm = vm_of(model)
        self.errors: dict[str, str] = {}
        self.latency = 0.0
        self.connected_lag = IS_CONNECTED_LAG
        self.calls: list[tuple[str, tuple[object, ...]]] = []
        self.rejected: list[str] = []
        self.program: str | None = None
        self.loaded_scripts: list[str] = []
        self.max_in_flight = 0
        #: The program variables this medulla knows (declared by programs it loaded).
        self.known: set[str] = set()
        #: Variables of the robot's firmware besides the sensors and motors, read from
        #: ``model.variables``: a real Thymio also declares ``_vbat``; only ``_fwversion``, as
        #: Aseba Playground's.
        self.native: set[str] = {FWVERSION}
        self._in_flight = 0
        self._hang = False
        self._robot_connected = True
        self._lost_at = 0.0
        self._closing = False
        self._wake = asyncio.Event()
        self._idle = asyncio.Event()
        self._idle.set()
        self.interface = _AsebaNetwork(self)

    @property
    def hang(self) -> bool:
        """Whether ``GetVariable`` calls wait forever (until this is cleared or the fake closes)."""
        return self._hang

    @hang.setter
    def hang(self, value: bool) -> None:
        self._hang = value
        self._wake_waiters()

    @property
    def robot_connected(self) -> bool:
        """Whether the robot is reachable."""
        return self._robot_connected

    def disconnect_robot(self) -> None:
        """The robot goes away: reads hang, writes are dropped, the node stays listed."""
        if self._robot_connected:
            self._lost_at = time.monotonic()
        self._robot_connected = False

    def reconnect_robot(self) -> None:
        """The robot is back (the real medulla never does this; useful in tests)."""
        self._robot_connected = True
        self._wake_waiters()

    def close(self) -> None:
        """Release every waiting ``GetVariable`` with an error."""
        self._closing = True
        self._wake_waiters()

    async def wait_idle(self) -> None:
        """Return once no ``GetVariable`` is pending."""
        await self._idle.wait()

    def _wake_waiters(self) -> None:
        self._wake.set()
        self._wake = asyncio.Event()

    # -- the methods, called by the D-Bus interface ---------------------------------------------

    def _check_node(self, node: str) -> None:
        if node != self.node:
            raise DBusError(ErrorType.INVALID_ARGS, f"node {node} does not exists")

    def _known(self, variable: str) -> bool:
        return (
            variable in MOTOR_TARGETS
            or variable in self.known
            or variable in self.native
            or variable == "prox.horizontal"
            or variable in GROUND_VARIABLES
        )

    def _lookup(self, variable: str) -> list[int]:
        if variable in self.errors:
            raise DBusError(ErrorType.FAILED, self.errors[variable])
        if not self._known(variable):
            raise DBusError(
                ErrorType.INVALID_ARGS, f"variable {variable} does not exists in node {self.node}"
            )
        if variable == "prox.horizontal":
            return self.model.prox_horizontal()
        if variable in GROUND_VARIABLES:
            return self.model.ground(variable)
        if variable in MOTOR_TARGETS:
            return [model_target(self.model, variable)]
        return list(self.model.variables.get(variable, [0]))

    async def get_variable(self, node: str, variable: str) -> list[int]:
        """``GetVariable``: check the names at once, then answer when the robot does."""
        self.calls.append(("GetVariable", (node, variable)))
        self._check_node(node)
        self._lookup(variable)  # unknown names fail at once, as in medulla
        self._in_flight += 1
        self.max_in_flight = max(self.max_in_flight, self._in_flight)
        self._idle.clear()
        try:
            while (self._hang or not self._robot_connected) and not self._closing:
                await self._wake.wait()
            if self._closing:
                raise DBusError(ErrorType.NO_REPLY, "the fake medulla shut down")
            if self.latency:
                await asyncio.sleep(self.latency)
            return _int16(self._lookup(variable))  # sampled when the robot answers
        finally:
            self._in_flight -= 1
            if not self._in_flight:
                self._idle.set()

    def set_variable(self, node: str, variable: str, values: list[int]) -> None:
        """``SetVariable``: store the values; motor targets go to the model, ``leds.top`` to its
        ``set_top_led`` if it has one. An unknown node or variable is recorded and raised (a
        caller that expects no reply never sees it)."""
        self.calls.append(("SetVariable", (node, variable, list(values))))
        if node != self.node:
            self.rejected.append(f"SetVariable: node {node} does not exists")
            raise DBusError(ErrorType.INVALID_ARGS, f"node {node} does not exists")
        if not self._known(variable):
            self.rejected.append(f"SetVariable: variable {variable} does not exists")
            raise DBusError(
                ErrorType.INVALID_ARGS, f"variable {variable} does not exists in node {self.node}"
            )
        if not self._robot_connected:
            return  # medulla writes into the void
        self.model.variables[variable] = _int16(values)
        if variable in MOTOR_TARGETS and values:
            self.model.set_target(MOTOR_TARGETS[variable], _int16(values)[0])
        record = getattr(self.model, "set_top_led", None)
        if variable == LEDS_TOP and record is not None:
            record(_int16(values))

    def load_scripts(self, path: str) -> None:
        """``LoadScripts``: load the ``.aesl`` program into the robot's VM.

        A missing file or a malformed program raises a D-Bus error, which reaches only a caller
        that expects a reply, as with the real medulla.
        """
        self.calls.append(("LoadScripts", (path,)))
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError:
            self.rejected.append(f"LoadScripts: file {path} does not exists")
            raise DBusError(ErrorType.INVALID_ARGS, f"file {path} does not exists") from None
        try:
            root = ET.fromstring(text)
        except ET.ParseError as exc:
            self.rejected.append(f"LoadScripts: {exc}")
            raise DBusError(ErrorType.FAILED, f"error while parsing {path}: {exc}") from None
        nodes = [n for n in root.iter("node") if n.get("name") == self.node]
        if root.tag != "network" or not nodes:
            # medulla ignores a program for other nodes; it only says so on its stderr
            self.rejected.append(f"LoadScripts: no script for node {self.node} in {path}")
            return
        code = nodes[0].text or ""
        if self._robot_connected:
            self.known = set(self.vm.load(code))
        self.program = code
        self.loaded_scripts.append(path)

    def is_connected(self, node: str) -> bool:
        """``IsConnected``: whether the robot is reachable, :attr:`connected_lag` late."""
        self.calls.append(("IsConnected", (node,)))
        self._check_node(node)
        if self._robot_connected:
            return True
        return time.monotonic() - self._lost_at < self.connected_lag


class _AsebaNetwork(ServiceInterface):
    """The D-Bus face of :class:`FakeMedulla` (method names and signatures as medulla's).

    The string annotations are D-Bus signatures read by dbus-fast, not Python types (hence the
    ``noqa`` and ``type: ignore``); this module avoids ``from __future__ import annotations`` so
    they stay plain.
    """

    def __init__(self, fake: FakeMedulla) -> None:
        super().__init__(ASEBA_INTERFACE)
        self._fake = fake

    @dbus_method()
    def GetNodesList(self) -> "as":  # type: ignore[valid-type]  # noqa: F722
        self._fake.calls.append(("GetNodesList", ()))
        return [self._fake.node]

    @dbus_method()
    async def GetVariable(self, node: "s", variable: "s") -> "an":  # type: ignore[name-defined]  # noqa: F821
        return await self._fake.get_variable(node, variable)

    @dbus_method()
    def SetVariable(self, node: "s", variable: "s", data: "an"):  # type: ignore[name-defined]  # noqa: F821
        self._fake.set_variable(node, variable, data)

    @dbus_method()
    def IsConnected(self, node: "s") -> "b":  # type: ignore[name-defined]  # noqa: F821
        return self._fake.is_connected(node)

    @dbus_method()
    def LoadScripts(self, path: "s"):  # type: ignore[name-defined]  # noqa: F821
        self._fake.load_scripts(path)


def _die_with_parent() -> None:
    # Runs in the child before exec: SIGKILL of the simulator skips our clean-up, and a daemon
    # must not outlive it. PR_SET_PDEATHSIG (1) is Linux's; elsewhere the daemon may linger.
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)


def bus_config(listen: str) -> str:
    """A ``dbus-daemon`` configuration for a private test bus listening on ``listen`` (a D-Bus
    address such as ``unix:path=/tmp/x/socket``); anyone may own names and eavesdrop."""
    return _BUS_CONFIG.format(listen=listen)


@contextlib.asynccontextmanager
async def private_bus(*, abstract: bool = False) -> AsyncIterator[str]:
    """Start a private ``dbus-daemon`` for the duration of the context; yields its address.

    With ``abstract`` the socket is in Linux's abstract namespace instead of a directory under
    /tmp, so that a process with a private /tmp (systemd's ``PrivateTmp=yes``) reaches it too.
    """
    executable = shutil.which("dbus-daemon")
    if executable is None:
        raise FileNotFoundError("dbus-daemon is not installed (Debian package dbus-daemon)")
    with tempfile.TemporaryDirectory(prefix="fake-dbus-") as tmp:
        config = Path(tmp) / "bus.conf"
        listen = (
            f"unix:abstract=minimize-surprise-{Path(tmp).name}"
            if abstract
            else f"unix:path={Path(tmp) / 'socket'}"
        )
        config.write_text(bus_config(listen), encoding="utf-8")
        with open(Path(tmp) / "stderr", "wb") as stderr:
            process = await asyncio.create_subprocess_exec(
                executable,
                f"--config-file={config}",
                "--print-address",
                "--nofork",
                "--nopidfile",
                stdin=asyncio.subprocess.DEVNULL,
                stdout=asyncio.subprocess.PIPE,
                stderr=stderr,
                preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
            )
            try:
                assert process.stdout is not None
                async with asyncio.timeout(DAEMON_TIMEOUT):
                    line = await process.stdout.readline()
                if not line:
                    raise RuntimeError(
                        "dbus-daemon did not start: "
                        + (Path(tmp) / "stderr").read_text(errors="replace").strip()
                    )
                yield line.decode().strip()
            finally:
                if process.returncode is None:
                    process.terminate()
                    try:
                        async with asyncio.timeout(DAEMON_TIMEOUT):
                            await process.wait()
                    except TimeoutError:
                        process.kill()
                        await process.wait()


@contextlib.asynccontextmanager
async def serve_fake_medulla(
    address: str,
    model: ThymioModel,
    *,
    node: str = "thymio-II",
    medulla: Callable[[Any, str], FakeMedulla] | None = None,
    keep_vm: bool = False,
) -> AsyncIterator[FakeMedulla]:
    """Serve a :class:`FakeMedulla` for ``model`` on the bus at ``address`` during the context.

    ``medulla(model, node)`` builds it (default :class:`FakeMedulla`; the simulator's waiting
    medulla is a subclass). Leaving the context ends this medulla; the robot's program stops
    too unless ``keep_vm`` (a medulla restart: serve another one for the same model, and close
    ``vm_of(model)`` at the end).
    """
    bus = await MessageBus(bus_address=address).connect()
    fake = (medulla or FakeMedulla)(model, node)
    try:
        bus.export(ASEBA_PATH, fake.interface)
        reply = await bus.request_name(ASEBA_SERVICE)
        if reply != RequestNameReply.PRIMARY_OWNER:
            raise RuntimeError(f"cannot own {ASEBA_SERVICE} on {address}: {reply}")
        yield fake
    finally:
        # Answer the hung calls (with an error) before hanging up, so no task is left pending.
        fake.close()
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(DAEMON_TIMEOUT):
                await fake.wait_idle()
        for _ in range(3):  # let the released calls' reply callbacks run
            await asyncio.sleep(0)
        if not keep_vm:
            fake.vm.close()
        # The name released and its release confirmed before hanging up: a call sent right after
        # then finds no medulla at once, as when medulla is gone, instead of racing the daemon's
        # handling of the disconnect (a call routed to the closing connection times out).
        with contextlib.suppress(Exception):
            async with asyncio.timeout(DAEMON_TIMEOUT):
                await bus.release_name(ASEBA_SERVICE)
        bus.disconnect()
        with contextlib.suppress(Exception):
            await bus.wait_for_disconnect()
