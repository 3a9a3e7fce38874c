"""The Thymio II base through asebamedulla on D-Bus, with ``dbus-fast`` (docs/thymio.md).

:class:`ThymioBase` is a body part: it reports the 7 horizontal IR and the 2 ground sensors and
drives the wheels. Facts about the real medulla that shape this code:

- ``GetVariable`` never answers once the robot is gone, and no D-Bus timeout fires, so every call
  is bounded by ``asyncio.timeout`` (:meth:`ThymioBase._call`, the one place where D-Bus replies,
  errors and timeouts become :class:`~minimize_surprise.errors.HardwareError`). It waits for the
  robot's answer, so the IR and ground reads go out concurrently, and a read that answers proves the
  robot is there.
- ``SetVariable`` is declared no-reply and a failed write is silent. ``IsConnected`` stays true
  for seconds after the robot went away, so a stop is confirmed by reading the motor targets back
  from the robot (:meth:`ThymioBase.stop`).
- medulla never reconnects to a robot that went away, and a restarted medulla does not know the
  variables of the program an earlier medulla loaded, although that program still runs on the
  robot. So the base *attaches* to one medulla process: it addresses that process by its unique
  bus name and loads its program (the failsafe, or an empty one) through it. Calls to a medulla
  that ended fail at once, and driving resumes only after :meth:`ThymioBase.recover` attached to
  the new one and loaded the program again. A stop goes to whichever medulla owns the name now.
- ``LoadScripts`` answers errors (a missing file, a compile error) when the caller asks for a
  reply, so the program is loaded expecting one and medulla's own reason is reported.

``dbus-fast`` is imported inside the methods so that importing ``drivers`` does not need it.

Why one file of over 600 lines: every call goes through one bounded D-Bus helper and depends on
one state, the medulla attached to and its program, which the facts above shape together.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import re
import signal
import time
from collections.abc import Awaitable, Callable, Sequence
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar
from xml.sax.saxutils import quoteattr

from drivers.body import clamp_unit, led_level
from drivers.config import CALL_TIMEOUT, PROGRAM_NODE, ThymioConfig
from drivers.parts import gather_all
from minimize_surprise.errors import (
    DBusReplyError,
    HardwareError,
    HardwareTimeoutError,
    RobotUnreachableError,
)
from minimize_surprise.files import write_atomic
from minimize_surprise.sensors import GROUND_SENSORS, IR_SENSORS

if TYPE_CHECKING:
    import numpy as np
    from dbus_fast.aio import MessageBus

__all__ = ["CALL_TIMEOUT", "MedullaRestarter", "ThymioBase", "ThymioConfig", "end_process"]

T = TypeVar("T")
log = logging.getLogger(__name__)

ASEBA_SERVICE = "ch.epfl.mobots.Aseba"
ASEBA_PATH = "/"
ASEBA_INTERFACE = "ch.epfl.mobots.AsebaNetwork"
DBUS_SERVICE = "org.freedesktop.DBus"
DBUS_PATH = "/org/freedesktop/DBus"
PROX_HORIZONTAL = "prox.horizontal"
MOTOR_LEFT = "motor.left.target"
MOTOR_RIGHT = "motor.right.target"
#: The top RGB LED: three values 0..LED_MAX (the firmware's scale). Aseba Playground's Thymio
#: does not declare it (docs/thymio.md).
LEDS_TOP = "leds.top"
LED_MAX = 32
#: Raw horizontal IR of an obstacle in contact; larger readings clip to 1.
IR_MAX = 4500.0
#: Full scale of the ground sensors' 10-bit readings.
GROUND_MAX = 1023.0
#: The firmware's battery measurement, two raw values; their sum / VBAT_SCALE is about the
#: battery's voltage (docs/thymio.md). Aseba Playground's Thymio does not declare it.
VBAT = "_vbat"
VBAT_SCALE = 397.8
#: The firmware's version, two values: the version in ``[0]`` (Aseba Playground's Thymio answers
#: ``[11, 0]``; docs/thymio.md). Read once when the agent says Hello (docs/fleet.md).
FWVERSION = "_fwversion"
#: How medulla answers ``GetVariable`` for a name the robot does not declare, at once and without
#: asking the robot: ``variable _vbat does not exists in node thymio-II`` (sic).
UNKNOWN_VARIABLE_ERROR = "org.freedesktop.DBus.Error.InvalidArgs"
#: The programs shipped next to this module, and the variable the host refreshes.
FAILSAFE_PROGRAM = "failsafe.aesl"
EMPTY_PROGRAM = "empty.aesl"
HEARTBEAT = "heartbeat"
#: Seconds per count of ``heartbeat``: the program's ``timer.period[0] = 100`` (ms).
FAILSAFE_TICK = 0.1
#: Seconds to wait for the socket to close on disconnect; nothing useful is left to wait for.
DISCONNECT_TIMEOUT = 1.0
#: Seconds a medulla we have just seen gets to find the robot before :meth:`ThymioBase.recover`
#: ends it: medulla opens the serial port at start and lists the node once the robot described
#: itself, well under a second with a robot present.
MEDULLA_GRACE = 5.0
#: D-Bus errors of a call to a bus name nobody owns: the medulla we attached to has ended.
_GONE_ERRORS = frozenset(
    {"org.freedesktop.DBus.Error.ServiceUnknown", "org.freedesktop.DBus.Error.NameHasNoOwner"}
)
#: D-Bus error of a call whose callee left the bus before answering.
_NO_REPLY = "org.freedesktop.DBus.Error.NoReply"

#: Ends the medulla process with the given unique bus name and process id.
MedullaRestarter = Callable[[str, int], Awaitable[None]]


class ThymioBase:
    """The Thymio II part of a body: IR and ground sensors, wheel motors.

    Call :meth:`open` first (connects, attaches to medulla: finds the node, stops the motors,
    loads the program); :meth:`close` stops the motors and disconnects and never raises. After a
    :class:`~minimize_surprise.errors.RobotUnreachableError`, :meth:`recover` attaches again (to a
    new medulla, ending one that lost the robot when ``config.restart_medulla`` is set).

    ``end_medulla`` is how a medulla that lost the robot is ended; the default sends SIGTERM to
    its process (:func:`end_process`). Tests whose fake medulla runs in their own process pass
    their own.
    """

    sensors: tuple[str, ...] = IR_SENSORS + GROUND_SENSORS

    def __init__(
        self, config: ThymioConfig | None = None, *, end_medulla: MedullaRestarter | None = None
    ) -> None:
        self.config = config or ThymioConfig()
        self._end_medulla = end_medulla or end_process
        self._bus: MessageBus | None = None
        #: The unique bus name of the medulla we attached to (None until attached).
        self._medulla: str | None = None
        self._failsafe_active = False
        #: When each medulla (unique name) was first seen, for :data:`MEDULLA_GRACE`.
        self._first_seen: dict[str, float] = {}
        # round() first: 1.0 / 0.1 is 10.000000000000002 in floating point.
        self.heartbeat_ticks = math.ceil(round(self.config.failsafe_timeout / FAILSAFE_TICK, 6))
        #: The motor targets last sent (raw motor units).
        self.last_targets: tuple[int, int] = (0, 0)

    @property
    def is_open(self) -> bool:
        """Whether the D-Bus connection is up."""
        return self._bus is not None and self._bus.connected

    @property
    def attached(self) -> str | None:
        """The unique bus name of the medulla this base drives through, or None."""
        return self._medulla

    @property
    def failsafe_active(self) -> bool:
        """Whether the failsafe program was loaded and is refreshed on every motor command."""
        return self._failsafe_active

    def targets(self, left: float, right: float) -> tuple[int, int]:
        """Motor targets for normalised speeds: clamp to [-1, 1] (NaN is 0), scale (by
        ``speed_scale`` over the wheel's calibrated scale), round, clamp."""
        limit = self.config.max_target

        def one(value: float, wheel: float) -> int:
            target = round(clamp_unit(value) * self.config.speed_scale / wheel)
            return max(-limit, min(limit, target))

        return one(left, self.config.wheel_left), one(right, self.config.wheel_right)

    # -- lifecycle ---------------------------------------------------------------------------------

    async def connect(self) -> None:
        """Connect to the D-Bus bus only (enough for :meth:`stop`); idempotent."""
        if self._bus is not None and self._bus.connected:
            return
        bus, self._bus = self._bus, None
        await _disconnect(bus)
        self._bus = await self._connect()

    async def open(self) -> None:
        """Connect and attach to medulla (see :meth:`attach`); idempotent.

        Raises :class:`HardwareError` with what is missing (no medulla, no node, robot gone,
        program not loaded); the connection is closed again then.
        """
        if self._medulla is not None and self.is_open:
            return
        await self.connect()
        try:
            await self.attach()
        except BaseException:
            bus, self._bus = self._bus, None
            await _disconnect(bus)
            raise

    async def attach(self) -> None:
        """Attach to the medulla that owns the service name now.

        Checks that it lists the node and that the robot answers, stops the motors, loads the
        program (the failsafe or an empty one) expecting medulla's reply, and only then drives
        through this medulla. Raises :class:`RobotUnreachableError` when medulla or the robot is
        missing, :class:`HardwareError` when the program does not load.
        """
        self._medulla = None
        self._failsafe_active = False
        owner = await self._owner()
        node = self.config.node
        try:
            (nodes,) = await self._call("GetNodesList", to=owner)
        except HardwareTimeoutError:
            raise
        except HardwareError as exc:
            raise RobotUnreachableError(
                f"Thymio: asebamedulla does not answer on the D-Bus {self.config.bus} bus "
                f"({exc}); is it running there?"
            ) from exc
        if node not in nodes:
            listed = ", ".join(map(repr, nodes)) or "none"
            raise RobotUnreachableError(
                f"Thymio: asebamedulla has no node {node!r} (nodes: {listed}); "
                "is the robot plugged in and switched on?"
            )
        (connected,) = await self._call("IsConnected", "s", [node], to=owner)
        if not connected:
            raise RobotUnreachableError(
                f"Thymio: node {node!r} is known to asebamedulla but disconnected"
            )
        await self._stop_through(owner)
        await self._load_program(owner)
        self._medulla = owner
        self._failsafe_active = self.config.failsafe
        log.info(
            "Thymio: attached to asebamedulla %s (%s)",
            owner,
            "failsafe loaded" if self.config.failsafe else "empty program loaded",
        )

    async def recover(self) -> None:
        """Attach again after the robot or medulla was lost; raises while that is not possible.

        A medulla that cannot reach the robot never will (it does not reconnect), so when
        ``config.restart_medulla`` is set and it had :data:`MEDULLA_GRACE` seconds to find the
        robot, it is ended, for its service to start a fresh one; the next call attaches to that.
        """
        await self.connect()
        try:
            await self.attach()
        except (RobotUnreachableError, HardwareTimeoutError):
            # Lost the robot, or hung: either way this medulla will not come back by itself.
            await self._restart_stale_medulla()
            raise

    async def close(self) -> None:
        """Stop the motors (attempted even on a broken bus), then disconnect. Never raises."""
        bus = self._bus
        if bus is None:
            return
        try:
            try:
                await self.stop()
            except Exception as exc:  # a broken bus is a common reason to close
                log.warning("Thymio: stopping the motors on close failed: %s", exc)
        finally:
            self._bus = None
            self._medulla = None
            self._failsafe_active = False
            await _disconnect(bus)

    # -- sensors -----------------------------------------------------------------------------------

    async def read_ir(self) -> np.ndarray:
        """The 7 horizontal IR values (front left..right, back left, right): raw / 4500, clipped."""
        import numpy as np  # here: --stop-motors imports this module and must stay light

        raw = await self._get(PROX_HORIZONTAL, len(IR_SENSORS))
        return np.clip(np.asarray(raw, dtype=float) / IR_MAX, 0.0, 1.0)

    async def read_ground(self) -> np.ndarray:
        """The 2 ground values (left, right) of the configured variable, raw / 1023 in [0, 1]."""
        import numpy as np  # see read_ir

        raw = await self._get(self.config.ground, len(GROUND_SENSORS))
        return np.clip(np.asarray(raw, dtype=float) / GROUND_MAX, 0.0, 1.0)

    async def read(self) -> np.ndarray:
        """IR then ground (9 values), both requested at once since each waits for the robot."""
        import numpy as np  # see read_ir

        ir, ground = await gather_all(self.read_ir(), self.read_ground())
        return np.concatenate([ir, ground])

    async def read_battery(self) -> float | None:
        """The battery's voltage from ``_vbat``, or None when the robot does not declare it.

        A robot that does not answer raises as any read does (:class:`RobotUnreachableError` or
        :class:`HardwareTimeoutError`): an unknown battery is never a lost robot, nor the reverse.
        """
        try:
            raw = await self._get(VBAT, 2)
        except DBusReplyError as exc:
            if exc.name == UNKNOWN_VARIABLE_ERROR:
                return None
            raise
        return round((raw[0] + raw[1]) / VBAT_SCALE, 3)

    async def read_firmware(self) -> int | None:
        """The firmware's version (``_fwversion[0]``), or None when the robot does not declare
        it; a robot that does not answer raises as any read does."""
        try:
            raw = await self._get(FWVERSION)
        except DBusReplyError as exc:
            if exc.name == UNKNOWN_VARIABLE_ERROR:
                return None
            raise
        return int(raw[0]) if raw else None

    # -- motors ------------------------------------------------------------------------------------

    async def set_speeds(self, left: float, right: float) -> tuple[int, int]:
        """Drive the wheels at normalised speeds; returns the motor targets sent.

        Only through the attached medulla, so never before the program is loaded in it. With the
        failsafe active the heartbeat is refreshed first, so the program never sees fresh targets
        with an expired heartbeat.
        """
        medulla = self._attached_medulla()
        targets = self.targets(left, right)
        if self._failsafe_active:
            await self._set(HEARTBEAT, [self.heartbeat_ticks], to=medulla)
        await self._set(MOTOR_LEFT, [targets[0]], to=medulla)
        await self._set(MOTOR_RIGHT, [targets[1]], to=medulla)
        self.last_targets = targets
        return targets

    async def stop(self) -> None:
        """Set both motor targets to 0 and confirm it by reading them back from the robot.

        The stop goes to whichever medulla owns the service name now (a restarted one too). The
        writes are no-reply and medulla drops writes to a robot it lost, so the read-back is what
        shows the stop arrived: :class:`RobotUnreachableError` when the robot does not answer.
        """
        await self._stop_through(ASEBA_SERVICE)
        self.last_targets = (0, 0)

    async def set_top_led(self, red: float, green: float, blue: float) -> None:
        """Light the top LED: each channel in [0, 1] becomes 0..32 of ``leds.top``.

        Unlike the motors' writes this one asks medulla for its answer: medulla then says at once
        when the robot has no such variable (Aseba Playground's Thymio), which a no-reply write
        would swallow. It never waits for the robot (medulla answers a write itself).
        :class:`DBusReplyError` names a robot without ``leds.top``.
        """
        values = [round(led_level(c) * LED_MAX) for c in (red, green, blue)]
        try:
            await self._call(
                "SetVariable",
                "ssan",
                [self.config.node, LEDS_TOP, values],
                to=self._attached_medulla(),
            )
        except DBusReplyError as exc:
            if exc.name == UNKNOWN_VARIABLE_ERROR:
                raise DBusReplyError(
                    f"Thymio: the robot has no {LEDS_TOP} variable (Aseba Playground's Thymio "
                    "has none): no LED signal",
                    exc.name,
                ) from exc
            raise

    async def is_connected(self) -> bool:
        """Whether the attached medulla sees the robot; also a barrier for earlier writes.

        medulla keeps answering true for seconds after the robot went away: not a proof.
        """
        (connected,) = await self._call(
            "IsConnected", "s", [self.config.node], to=self._attached_medulla()
        )
        return bool(connected)

    # -- medulla and programs ---------------------------------------------------------------------

    async def _stop_through(self, medulla: str) -> None:
        await self._set(MOTOR_LEFT, [0], to=medulla)
        await self._set(MOTOR_RIGHT, [0], to=medulla)
        try:
            left, right = await gather_all(
                self._get(MOTOR_LEFT, 1, to=medulla), self._get(MOTOR_RIGHT, 1, to=medulla)
            )
        except HardwareTimeoutError as exc:
            raise RobotUnreachableError(
                f"Thymio: stop not confirmed: the robot {self.config.node!r} does not answer "
                f"({exc})"
            ) from exc
        except RobotUnreachableError as exc:
            raise RobotUnreachableError(f"Thymio: stop not confirmed: {exc}") from exc
        if left[0] or right[0]:
            raise HardwareError(
                f"Thymio: stop not confirmed: the motor targets read back as ({left[0]}, "
                f"{right[0]})"
            )

    async def _owner(self) -> str:
        """The unique bus name owning the medulla service now."""
        try:
            (owner,) = await self._call(
                "GetNameOwner", "s", [ASEBA_SERVICE], to=DBUS_SERVICE, path=DBUS_PATH
            )
        except HardwareTimeoutError:
            raise
        except HardwareError as exc:
            raise RobotUnreachableError(
                f"Thymio: asebamedulla is not running on the D-Bus {self.config.bus} bus ({exc})"
            ) from exc
        self._first_seen.setdefault(owner, time.monotonic())
        return owner

    async def _load_program(self, medulla: str) -> None:
        name = FAILSAFE_PROGRAM if self.config.failsafe else EMPTY_PROGRAM
        config = self.config
        path = await asyncio.to_thread(program_path, name, config.node, config.program_dir)
        what = "the failsafe program" if self.config.failsafe else "an empty program"
        try:
            await self._call("LoadScripts", "s", [path], to=medulla)
        except HardwareTimeoutError:
            raise
        except HardwareError as exc:
            if _NO_REPLY in str(exc):
                from drivers.medulla_locale import abort_reason  # only when medulla aborted

                raise HardwareError(abort_reason(what, path)) from exc
            raise HardwareError(
                f"Thymio: asebamedulla could not load {what} {path}: {exc}"
            ) from exc
        if not self.config.failsafe:
            return
        # A program for another node name is ignored with only a line on medulla's stderr; the
        # variable it declares shows that it was loaded into this node.
        try:
            await self._get(HEARTBEAT, 1, to=medulla)
        except HardwareTimeoutError:
            raise
        except HardwareError as exc:
            raise HardwareError(
                f"Thymio: the failsafe program {path} did not load into node "
                f"{self.config.node!r} ({exc})"
            ) from exc

    async def _restart_stale_medulla(self) -> None:
        if not self.config.restart_medulla or self._bus is None:
            return
        try:
            owner = await self._owner()
        except HardwareError:
            return  # no medulla now: its service is starting a fresh one
        age = time.monotonic() - self._first_seen[owner]
        if age < MEDULLA_GRACE:
            return
        try:
            (pid,) = await self._call(
                "GetConnectionUnixProcessID", "s", [owner], to=DBUS_SERVICE, path=DBUS_PATH
            )
            log.warning(
                "Thymio: asebamedulla %s (pid %d) cannot reach the robot and never reconnects: "
                "ending it so that its service starts a fresh one",
                owner,
                pid,
            )
            await self._end_medulla(owner, int(pid))
        except (HardwareError, OSError) as exc:
            log.error("Thymio: cannot end asebamedulla %s: %s", owner, exc)

    def _attached_medulla(self) -> str:
        if self._medulla is None:
            raise RobotUnreachableError(
                "Thymio: not attached to asebamedulla (it ended or the robot was lost); "
                "waiting for recovery"
            )
        return self._medulla

    # -- D-Bus -------------------------------------------------------------------------------------

    async def _get(self, variable: str, length: int | None = None, *, to: str = "") -> list[int]:
        (values,) = await self._call(
            "GetVariable", "ss", [self.config.node, variable], to=to or self._attached_medulla()
        )
        if length is not None and len(values) != length:
            raise HardwareError(f"Thymio: {variable} has {len(values)} values, expected {length}")
        return list(values)

    async def _set(self, variable: str, values: Sequence[int], *, to: str = "") -> None:
        await self._call(
            "SetVariable",
            "ssan",
            [self.config.node, variable, list(values)],
            reply=False,
            to=to or self._attached_medulla(),
        )

    async def _connect(self) -> MessageBus:
        from dbus_fast import BusType
        from dbus_fast.aio import MessageBus

        where = self.config.bus

        async def connect() -> MessageBus:
            if where in ("session", "system"):
                bus_type = BusType.SESSION if where == "session" else BusType.SYSTEM
                return await MessageBus(bus_type=bus_type).connect()
            return await MessageBus(bus_address=where).connect()

        try:
            return await _bounded(
                f"Thymio: connect to the D-Bus {where} bus", connect(), self.config.connect_timeout
            )
        except HardwareError as exc:
            cause = exc.__cause__
            if isinstance(cause, FileNotFoundError | ConnectionRefusedError | PermissionError):
                # A configuration to fix, not a robot that went away: say which key.
                raise HardwareError(
                    f"Thymio: no D-Bus to reach at {where} ({cause.strerror or cause}): check "
                    "body.thymio.bus in the agent's configuration, and that asebamedulla's bus "
                    "is up"
                ) from cause
            raise

    async def _call(
        self,
        member: str,
        signature: str = "",
        body: Sequence[Any] = (),
        *,
        to: str,
        path: str = ASEBA_PATH,
        reply: bool = True,
    ) -> list[Any]:
        """Call ``member`` on ``to``; the body of the answer (``[]`` for a no-reply call).

        A call to a medulla that is gone raises :class:`RobotUnreachableError`.
        """
        from dbus_fast import Message, MessageFlag, MessageType

        args = ", ".join(map(repr, body))
        operation = f"Thymio: asebamedulla {member}({args})"
        bus = self._bus
        if bus is None or not bus.connected:
            raise RobotUnreachableError(f"{operation}: the D-Bus connection is closed")
        message = Message(
            destination=to,
            path=path,
            interface=DBUS_SERVICE if to == DBUS_SERVICE else ASEBA_INTERFACE,
            member=member,
            signature=signature,
            body=list(body),
            flags=MessageFlag.NONE if reply else MessageFlag.NO_REPLY_EXPECTED,
        )

        async def exchange() -> list[Any]:
            if not reply:
                await bus.send(message)  # resolves once written to the socket
                return []
            answer = await bus.call(message)
            if answer is None:  # the connection closed while waiting
                raise RobotUnreachableError(f"{operation}: the D-Bus connection closed")
            if answer.message_type == MessageType.ERROR:
                text = answer.body[0] if answer.body else ""
                if answer.error_name in _GONE_ERRORS and to != DBUS_SERVICE:
                    if to == self._medulla:
                        # Nothing drives through a medulla that has not loaded our program.
                        self._medulla = None
                        self._failsafe_active = False
                    gone = "is not running" if to == ASEBA_SERVICE else f"{to} has ended"
                    raise RobotUnreachableError(
                        f"{operation}: asebamedulla {gone} ({answer.error_name})"
                    )
                raise DBusReplyError(
                    f"{operation}: {answer.error_name}: {text}", answer.error_name or ""
                )
            return list(answer.body)

        return await _bounded(operation, exchange(), self.config.timeout)


def program_path(name: str, node: str, directory: str | None) -> str:
    """The file medulla should load for the packaged program ``name`` and ``node``.

    For the Thymio's own node name the installed file itself; otherwise a copy written for that
    node into ``directory``, readable by every user (medulla may run as another; the programs
    hold no secret). Raises :class:`HardwareError` if it cannot be written.
    """
    source = resources.files("drivers").joinpath(name)
    if node == PROGRAM_NODE and directory is None and isinstance(source, Path):
        return str(source)
    if directory is None:
        raise HardwareError(
            f"Thymio: the Aseba program {name} is not a file medulla can read (a zipped "
            "install?): set body.thymio.program_dir to a directory both can use"
        )
    text = source.read_text("utf-8")
    text = text.replace(f'name="{PROGRAM_NODE}"', f"name={quoteattr(node)}")
    folder = Path(directory)
    target = folder / f"{Path(name).stem}-{re.sub(r'[^A-Za-z0-9._-]', '_', node)}.aesl"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        write_atomic(target, text.encode("utf-8"), durable=False, mode=0o644)
    except OSError as exc:
        raise HardwareError(f"Thymio: cannot write the Aseba program {target}: {exc}") from exc
    return str(target)


async def end_process(name: str, pid: int) -> None:
    """End the medulla process ``pid`` (bus name ``name``) with SIGTERM.

    Refuses to signal this very process (a medulla served in-process is a test double).
    """
    if pid == os.getpid():
        raise HardwareError(f"asebamedulla {name} runs in this process; not ending it")
    os.kill(pid, signal.SIGTERM)


async def _bounded(operation: str, call: Awaitable[T], timeout: float) -> T:
    """Await ``call`` within ``timeout``; every failure becomes a :class:`HardwareError`."""
    try:
        async with asyncio.timeout(timeout):
            return await call
    except TimeoutError:
        raise HardwareTimeoutError(operation, timeout) from None
    except HardwareError:
        raise
    except Exception as exc:  # dbus-fast raises OSError, EOFError, its own errors...
        raise HardwareError(f"{operation} failed: {exc!r}") from exc


async def _disconnect(bus: MessageBus | None) -> None:
    if bus is None:
        return
    try:
        bus.disconnect()
        async with asyncio.timeout(DISCONNECT_TIMEOUT):
            await bus.wait_for_disconnect()
    except Exception as exc:  # the connection may already be broken; nothing left to do
        log.debug("Thymio: disconnect: %r", exc)
