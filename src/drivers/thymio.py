"""The Thymio II base through asebamedulla on D-Bus (REFERENCE 4), with ``dbus-fast``.

:class:`ThymioBase` is a body part: it reports the 7 horizontal IR and the 2 ground sensors and
drives the wheels. Facts about the real medulla that shape this code:

- ``GetVariable`` never answers once the robot is gone, and no D-Bus timeout fires, so every call
  is bounded by ``asyncio.timeout`` (:meth:`ThymioBase._call`, the one place where D-Bus replies,
  errors and timeouts become :class:`~surprise.errors.HardwareError`).
- ``GetVariable`` waits for the robot's answer, so the IR and ground reads go out concurrently.
- ``SetVariable`` and ``LoadScripts`` are declared no-reply: they are sent with the
  ``NO_REPLY_EXPECTED`` flag, a failed write is silent, and a dead robot shows as read timeouts.
  :meth:`ThymioBase.is_connected` is a round trip on the same connection, so once it returns
  medulla has processed every earlier write (``stop()`` uses it to confirm the stop, and fails
  when medulla or the robot is gone).

``dbus-fast`` is imported inside the methods so that importing ``drivers`` does not need it.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import tempfile
from collections.abc import Awaitable, Sequence
from importlib import resources
from typing import TYPE_CHECKING, Any, TypeVar
from xml.sax.saxutils import quoteattr

import numpy as np

from drivers.body import clamp_unit
from drivers.config import CALL_TIMEOUT, ThymioConfig
from drivers.parts import gather_all
from surprise.errors import HardwareError, HardwareTimeoutError
from surprise.sensors import GROUND_SENSORS, IR_SENSORS

if TYPE_CHECKING:
    from dbus_fast.aio import MessageBus

__all__ = ["CALL_TIMEOUT", "ThymioBase", "ThymioConfig"]

T = TypeVar("T")
log = logging.getLogger(__name__)

ASEBA_SERVICE = "ch.epfl.mobots.Aseba"
ASEBA_PATH = "/"
ASEBA_INTERFACE = "ch.epfl.mobots.AsebaNetwork"
PROX_HORIZONTAL = "prox.horizontal"
MOTOR_LEFT = "motor.left.target"
MOTOR_RIGHT = "motor.right.target"
#: Raw horizontal IR of an obstacle in contact; larger readings clip to 1.
IR_MAX = 4500.0
#: Full scale of the ground sensors' 10-bit readings.
GROUND_MAX = 1023.0
#: The failsafe program shipped next to this module, and the variable the host refreshes.
FAILSAFE_PROGRAM = "failsafe.aesl"
HEARTBEAT = "heartbeat"
#: Seconds per count of ``heartbeat``: the program's ``timer.period[0] = 100`` (ms).
FAILSAFE_TICK = 0.1
#: The node name written in ``failsafe.aesl``; replaced when the configured node differs.
PROGRAM_NODE = "thymio-II"
#: Seconds to wait for the socket to close on disconnect; nothing useful is left to wait for.
DISCONNECT_TIMEOUT = 1.0


class ThymioBase:
    """The Thymio II part of a body: IR and ground sensors, wheel motors.

    Call :meth:`open` first (connects, finds the node, stops the motors, loads the failsafe if
    configured); :meth:`close` stops the motors and disconnects and never raises.
    """

    sensors: tuple[str, ...] = IR_SENSORS + GROUND_SENSORS

    def __init__(self, config: ThymioConfig | None = None) -> None:
        self.config = config or ThymioConfig()
        self._bus: MessageBus | None = None
        self._failsafe_active = False
        # round() first: 1.0 / 0.1 is 10.000000000000002 in floating point.
        self.heartbeat_ticks = math.ceil(round(self.config.failsafe_timeout / FAILSAFE_TICK, 6))
        #: The motor targets last sent (raw motor units).
        self.last_targets: tuple[int, int] = (0, 0)

    @property
    def is_open(self) -> bool:
        """Whether the D-Bus connection is up."""
        return self._bus is not None and self._bus.connected

    @property
    def failsafe_active(self) -> bool:
        """Whether the failsafe program was loaded and is refreshed on every motor command."""
        return self._failsafe_active

    def targets(self, left: float, right: float) -> tuple[int, int]:
        """Motor targets for normalised speeds: clamp to [-1, 1] (NaN is 0), scale, round, clamp."""
        limit = self.config.max_target

        def one(value: float) -> int:
            target = round(clamp_unit(value) * self.config.speed_scale)
            return max(-limit, min(limit, target))

        return one(left), one(right)

    # -- lifecycle ---------------------------------------------------------------------------------

    async def open(self) -> None:
        """Connect, check the node, stop the motors, load the failsafe if configured.

        Raises :class:`HardwareError` with what is missing (no medulla, no node, robot gone).
        """
        if self._bus is not None:
            return
        self._bus = await self._connect()
        node = self.config.node
        try:
            try:
                (nodes,) = await self._call("GetNodesList")
            except HardwareTimeoutError:
                raise
            except HardwareError as exc:
                raise HardwareError(
                    f"Thymio: asebamedulla does not answer on the D-Bus {self.config.bus} bus "
                    f"({exc}); is it running there?"
                ) from exc
            if node not in nodes:
                listed = ", ".join(map(repr, nodes)) or "none"
                raise HardwareError(
                    f"Thymio: asebamedulla has no node {node!r} (nodes: {listed}); "
                    "is the robot plugged in and switched on?"
                )
            if not await self.is_connected():
                raise HardwareError(f"Thymio: node {node!r} is known to medulla but disconnected")
            await self.stop()
            if self.config.failsafe:
                await self._load_failsafe()
                await self.stop()  # now also refreshes the heartbeat
        except BaseException:
            bus, self._bus = self._bus, None
            self._failsafe_active = False
            await _disconnect(bus)
            raise

    async def close(self) -> None:
        """Stop the motors (attempted even on a broken bus), then disconnect. Never raises."""
        bus = self._bus
        if bus is None:
            return
        try:
            try:
                await self.stop()  # confirmed by a round trip before we hang up
            except Exception as exc:  # a broken bus is a common reason to close
                log.warning("Thymio: stopping the motors on close failed: %s", exc)
        finally:
            self._bus = None
            self._failsafe_active = False
            await _disconnect(bus)

    # -- sensors -----------------------------------------------------------------------------------

    async def read_ir(self) -> np.ndarray:
        """The 7 horizontal IR values (front left..right, back left, right): raw / 4500, clipped."""
        raw = await self._get(PROX_HORIZONTAL, len(IR_SENSORS))
        return np.clip(np.asarray(raw, dtype=float) / IR_MAX, 0.0, 1.0)

    async def read_ground(self) -> np.ndarray:
        """The 2 ground values (left, right) of the configured variable, raw / 1023 in [0, 1]."""
        raw = await self._get(self.config.ground, len(GROUND_SENSORS))
        return np.clip(np.asarray(raw, dtype=float) / GROUND_MAX, 0.0, 1.0)

    async def read(self) -> np.ndarray:
        """IR then ground (9 values), both requested at once since each waits for the robot."""
        ir, ground = await gather_all(self.read_ir(), self.read_ground())
        return np.concatenate([ir, ground])

    # -- motors ------------------------------------------------------------------------------------

    async def set_speeds(self, left: float, right: float) -> tuple[int, int]:
        """Drive the wheels at normalised speeds; returns the motor targets sent.

        With the failsafe active the heartbeat is refreshed first, so the program never sees
        fresh targets with an expired heartbeat.
        """
        targets = self.targets(left, right)
        if self._failsafe_active:
            await self._set(HEARTBEAT, [self.heartbeat_ticks])
        await self._set(MOTOR_LEFT, [targets[0]])
        await self._set(MOTOR_RIGHT, [targets[1]])
        self.last_targets = targets
        return targets

    async def stop(self) -> None:
        """Set both motor targets to 0 and confirm that medulla delivered them to the robot.

        The writes are no-reply, so a stop that medulla dropped (robot gone, medulla gone) would
        otherwise look done; the :meth:`is_connected` round trip turns it into a
        :class:`HardwareError`, so callers (the watchdog) know to retry.
        """
        await self.set_speeds(0.0, 0.0)
        if not await self.is_connected():
            raise HardwareError(
                f"Thymio: stop not confirmed: medulla has lost the robot {self.config.node!r}"
            )

    async def is_connected(self) -> bool:
        """Whether medulla sees the robot; also a barrier for the writes sent before it."""
        (connected,) = await self._call("IsConnected", "s", [self.config.node])
        return bool(connected)

    # -- D-Bus -------------------------------------------------------------------------------------

    async def _get(self, variable: str, length: int | None = None) -> list[int]:
        (values,) = await self._call("GetVariable", "ss", [self.config.node, variable])
        if length is not None and len(values) != length:
            raise HardwareError(f"Thymio: {variable} has {len(values)} values, expected {length}")
        return list(values)

    async def _set(self, variable: str, values: Sequence[int]) -> None:
        await self._call(
            "SetVariable", "ssan", [self.config.node, variable, list(values)], reply=False
        )

    async def _load_failsafe(self) -> None:
        program = resources.files("drivers").joinpath(FAILSAFE_PROGRAM).read_text("utf-8")
        program = program.replace(f'name="{PROGRAM_NODE}"', f"name={quoteattr(self.config.node)}")
        # medulla reads the program from a path; a temporary copy carries the configured node name.
        path = await asyncio.to_thread(_write_temporary, program)
        try:
            await self._call("LoadScripts", "s", [path], reply=False)
            # LoadScripts is no-reply, so confirm through the variable the program declares:
            # medulla rejects the name if compiling or loading failed.
            try:
                await self._get(HEARTBEAT, 1)
            except HardwareTimeoutError:
                raise
            except HardwareError as exc:
                raise HardwareError(
                    f"Thymio: the failsafe program did not load ({exc}); medulla's LoadScripts "
                    "needs the en_US.UTF-8 locale and read access to the file"
                ) from exc
        finally:
            await asyncio.to_thread(_remove, path)
        self._failsafe_active = True

    async def _connect(self) -> MessageBus:
        from dbus_fast import BusType
        from dbus_fast.aio import MessageBus

        where = self.config.bus

        async def connect() -> MessageBus:
            if where in ("session", "system"):
                bus_type = BusType.SESSION if where == "session" else BusType.SYSTEM
                return await MessageBus(bus_type=bus_type).connect()
            return await MessageBus(bus_address=where).connect()

        return await _bounded(
            f"Thymio: connect to the D-Bus {where} bus", connect(), self.config.connect_timeout
        )

    async def _call(
        self, member: str, signature: str = "", body: Sequence[Any] = (), *, reply: bool = True
    ) -> list[Any]:
        """Call ``member`` on medulla; the body of the answer (``[]`` for a no-reply call)."""
        from dbus_fast import Message, MessageFlag, MessageType

        args = ", ".join(map(repr, body))
        operation = f"Thymio: asebamedulla {member}({args})"
        bus = self._bus
        if bus is None or not bus.connected:
            raise HardwareError(f"{operation}: the D-Bus connection is closed")
        message = Message(
            destination=ASEBA_SERVICE,
            path=ASEBA_PATH,
            interface=ASEBA_INTERFACE,
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
                raise HardwareError(f"{operation}: the D-Bus connection closed")
            if answer.message_type == MessageType.ERROR:
                text = answer.body[0] if answer.body else ""
                raise HardwareError(f"{operation}: {answer.error_name}: {text}")
            return list(answer.body)

        return await _bounded(operation, exchange(), self.config.timeout)


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


def _write_temporary(text: str) -> str:
    fd, path = tempfile.mkstemp(prefix="surprise-failsafe-", suffix=".aesl")
    with os.fdopen(fd, "w", encoding="utf-8") as file:
        file.write(text)
    # medulla may run as another user (on the system bus); the program holds no secret.
    os.chmod(path, 0o644)
    return path


def _remove(path: str) -> None:
    try:
        os.unlink(path)
    except OSError as exc:
        log.warning("Thymio: cannot remove %s: %s", path, exc)
