"""Emulated I2C chips served on a Unix socket: a served robot's force and light sensors.

On a robot the force sensor's ADS1115 and the two TSL45315 light sensors behind their TCA9548A
hang on the Pi's ``/dev/i2c-1``. For a robot served by ``surprise-sim-robots`` they are the
emulated chips of :mod:`standins.fake_i2c`, wired as deploy/examples/agent-object-manipulation.yaml
wires the real ones (:data:`SERVED_FORCE`, :data:`SERVED_LIGHT`), and :func:`serve_i2c_bridge`
answers the agent's :class:`~drivers.i2c_bridge.BridgeSMBus` on a socket of their own (the
protocol: :mod:`drivers.i2c_bridge`). The agent's real drivers decode the raw registers back into
normalised values, so the bridge checks the drivers as a robot would.

What the chips read (:class:`RobotChips`, sampled at every conversion):

- the ADS1115: ``force * full_scale_volts`` on the configured input pair (0 V on the others),
  so an unloaded blade is 0 V and the driver's zero, measured at open, is 0;
- each TSL45315: ``light * max_lux`` lux, which the chip counts in steps of its multiplier
  (4 lux at 100 ms: a resolution of 4 / 1024 of the normalised value).

:func:`world_chips` takes ``force`` and ``light.0``/``light.1`` from a simulated world's sensor
values of the robot's current step (with the world's noise, as a simulated body reads them);
:func:`constant_chips` reads fixed values (Aseba Playground: Enki has no blade, hence no force,
and no lamp).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import os
import tempfile
from collections.abc import AsyncIterator, Callable, Sequence
from pathlib import Path
from typing import Any

import msgspec

from drivers.config import ForceSensorConfig, LightSensorConfig, MuxConfig
from drivers.i2c_bridge import (
    HEADER_SIZE,
    MAX_ERROR_MESSAGE,
    BridgeReply,
    BridgeRequest,
    frame,
    message_size,
)
from minimize_surprise.sensors import FORCE_SENSORS, LIGHT_SENSORS
from simulator.world import World
from standins.fake_i2c import FakeADS1115, FakeI2C, FakeSMBus, FakeTCA9548A, FakeTSL45315

__all__ = [
    "HANG_UP_TIMEOUT",
    "MAX_SOCKET_PATH",
    "SERVED_FORCE",
    "SERVED_LIGHT",
    "SOCKET_DIR_PREFIX",
    "I2CBridgeServer",
    "RobotBridges",
    "RobotChips",
    "constant_chips",
    "force_volts",
    "light_lux",
    "serve_i2c_bridge",
    "served_parts",
    "world_chips",
]

log = logging.getLogger(__name__)

#: The force sensor of a served robot, wired as on the paper's extended Thymio
#: (deploy/examples/agent-object-manipulation.yaml): an ADS1115 at 0x48 on bus 1.
SERVED_FORCE = ForceSensorConfig(bus=1, address=0x48, inputs="AIN0-AIN1", pga_range_volts=0.256)
#: Its two light sensors: both TSL45315 answer at 0x29, so they sit behind channels 0 and 1 of a
#: TCA9548A at 0x70 on bus 1.
SERVED_LIGHT: tuple[LightSensorConfig, ...] = (
    LightSensorConfig(bus=1, mux=MuxConfig(address=0x70, channel=0)),
    LightSensorConfig(bus=1, mux=MuxConfig(address=0x70, channel=1)),
)
#: Seconds the server waits for its connections' handlers to end when it stops: a closed
#: connection ends its handler within a loop iteration or two.
HANG_UP_TIMEOUT = 1.0
#: The longest path a Unix socket's address holds (``sun_path`` is 108 bytes with its NUL).
MAX_SOCKET_PATH = 107


def served_parts(
    sensors: Sequence[str],
) -> tuple[ForceSensorConfig | None, tuple[LightSensorConfig, ...]]:
    """The I2C parts a robot carrying ``sensors`` needs: the force sensor if it has ``force``,
    as many light sensors as it has ``light.*`` sensors."""
    force = SERVED_FORCE if set(FORCE_SENSORS) & set(sensors) else None
    lights = sum(name in sensors for name in LIGHT_SENSORS)
    return force, SERVED_LIGHT[:lights]


def force_volts(value: float, config: ForceSensorConfig) -> float:
    """The bridge voltage that :class:`~drivers.force.ForceSensor` reads as ``value`` (0..1)."""
    return (-1.0 if config.invert else 1.0) * value * config.full_scale_volts


def light_lux(value: float, config: LightSensorConfig) -> float:
    """The illuminance that :class:`~drivers.light.LightSensor` reads as ``value`` (0..1)."""
    return value * config.max_lux


class RobotChips:
    """One robot's emulated I2C chips, wired as ``force`` and ``light`` say.

    ``read_force()`` and ``read_light(i)`` (normalised, 0..1) are called at every conversion.
    :attr:`i2c` holds the buses; :func:`serve_i2c_bridge` serves them.
    """

    def __init__(
        self,
        force: ForceSensorConfig | None,
        light: Sequence[LightSensorConfig],
        read_force: Callable[[], float],
        read_light: Callable[[int], float],
    ) -> None:
        self.force = force
        self.light = tuple(light)
        self.i2c = FakeI2C()
        if force is not None:

            def volts(inputs: str, config: ForceSensorConfig = force) -> float:
                # Only the bridge's input pair is wired; the other inputs float at 0 V.
                return force_volts(read_force(), config) if inputs == config.inputs else 0.0

            self._attach(force.bus, force.address, force.mux, FakeADS1115(voltage=volts))
        for i, config in enumerate(self.light):

            def lux(i: int = i, config: LightSensorConfig = config) -> float:
                return light_lux(read_light(i), config)

            self._attach(config.bus, config.address, config.mux, FakeTSL45315(lux=lux))

    def _attach(
        self,
        bus: int,
        address: int,
        mux: MuxConfig | None,
        device: FakeADS1115 | FakeTSL45315,
    ) -> None:
        fake_bus = self.i2c.bus(bus)
        if mux is None:
            fake_bus.attach(address, device)
            return
        multiplexer = fake_bus.devices.get(mux.address)
        if multiplexer is None:
            multiplexer = fake_bus.attach(mux.address, FakeTCA9548A())
        assert isinstance(multiplexer, FakeTCA9548A), f"0x{mux.address:02X} is no multiplexer"
        multiplexer.attach(mux.channel, address, device)


def world_chips(
    world: World,
    index: int,
    force: ForceSensorConfig | None,
    light: Sequence[LightSensorConfig],
) -> RobotChips:
    """Robot ``index``'s chips reading its ``force`` and ``light.<i>`` values from ``world``
    (the current step's, as its simulated body reads them)."""
    sensors = world.sensors
    wanted = (FORCE_SENSORS if force is not None else ()) + LIGHT_SENSORS[: len(light)]
    missing = [name for name in wanted if name not in sensors]
    if missing:
        raise ValueError(f"the world's robots carry no {', '.join(missing)} sensor")
    force_column = sensors.index(FORCE_SENSORS[0]) if force is not None else -1
    light_columns = [sensors.index(name) for name in LIGHT_SENSORS[: len(light)]]

    def read_force() -> float:
        return float(world.sensor_matrix()[index, force_column])

    def read_light(i: int) -> float:
        return float(world.sensor_matrix()[index, light_columns[i]])

    return RobotChips(force, light, read_force, read_light)


def constant_chips(
    force: ForceSensorConfig | None,
    light: Sequence[LightSensorConfig],
    *,
    force_value: float = 0.0,
    light_value: float = 0.0,
) -> RobotChips:
    """Chips that always read ``force_value`` and ``light_value`` (normalised)."""
    return RobotChips(force, light, lambda: force_value, lambda _: light_value)


class I2CBridgeServer:
    """The serving side of one bridge: answers each request with one call on :attr:`i2c`.

    :attr:`requests` counts the requests answered; :attr:`path` is the socket.
    """

    def __init__(self, path: Path, i2c: FakeI2C) -> None:
        self.path = path
        self.i2c = i2c
        self.requests = 0
        self._decoder = msgspec.msgpack.Decoder(BridgeRequest)
        self._writers: set[asyncio.StreamWriter] = set()
        self._handlers: set[asyncio.Task[None]] = set()

    def answer(self, request: BridgeRequest, handles: dict[int, FakeSMBus]) -> BridgeReply:
        """The reply to ``request`` on a connection that opened ``handles`` (bus -> handle)."""
        self.requests += 1
        try:
            if request.op == "open":
                handles.setdefault(request.bus, self.i2c.smbus(request.bus))
                return BridgeReply()
            handle = handles.get(request.bus)
            if handle is None:
                return BridgeReply(
                    errno=errno.EBADF, message=f"bus {request.bus} is not open on this connection"
                )
            return BridgeReply(value=self._call(handle, request))
        except OSError as exc:
            message = exc.strerror or str(exc)
            if exc.filename:
                message += f": {exc.filename}"
            return BridgeReply(errno=exc.errno or errno.EIO, message=message[:MAX_ERROR_MESSAGE])
        except ValueError as exc:  # an argument the chip's bus refuses, as smbus2 would
            return BridgeReply(errno=errno.EINVAL, message=str(exc)[:MAX_ERROR_MESSAGE])

    @staticmethod
    def _call(handle: FakeSMBus, request: BridgeRequest) -> int:
        address, register, value = request.address, request.register, request.value
        match request.op:
            case "read_byte_data":
                return handle.read_byte_data(address, register)
            case "read_word_data":
                return handle.read_word_data(address, register)
            case "write_byte_data":
                handle.write_byte_data(address, register, value)
            case "write_word_data":
                handle.write_word_data(address, register, value)
            case "write_byte":
                handle.write_byte(address, value)
        return 0

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Serve one connection (one client's bus handle) until it closes."""
        task = asyncio.current_task()
        assert task is not None
        self._handlers.add(task)
        self._writers.add(writer)
        handles: dict[int, FakeSMBus] = {}
        try:
            while True:
                size = message_size(await reader.readexactly(HEADER_SIZE))
                request = self._decoder.decode(await reader.readexactly(size))
                writer.write(frame(self.answer(request, handles)))
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError):
            pass  # the client closed its handle, or went away
        except (ValueError, msgspec.DecodeError) as exc:
            # Not our protocol: no reply could be trusted to match a request, so hang up.
            log.warning("I2C bridge %s: dropped a client that sent %s", self.path, exc)
        finally:
            self._handlers.discard(task)
            self._writers.discard(writer)
            for smbus in handles.values():
                smbus.close()
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()

    async def hang_up(self) -> None:
        """Close every client's connection (their next call fails, naming the socket) and wait,
        at most :data:`HANG_UP_TIMEOUT`, until each connection's handler has ended."""
        for writer in tuple(self._writers):
            writer.close()
        handlers = tuple(self._handlers)
        if handlers:
            # Each ends at once once its connection is closed; the bound is for a stuck peer.
            await asyncio.wait(handlers, timeout=HANG_UP_TIMEOUT)


@contextlib.asynccontextmanager
async def serve_i2c_bridge(path: str | Path, i2c: FakeI2C) -> AsyncIterator[I2CBridgeServer]:
    """Serve ``i2c``'s buses on the Unix socket ``path`` for the duration of the context; the
    socket file is removed afterwards (a stale one is replaced). Raises ``OSError`` if the path
    is too long for a Unix socket or cannot be bound."""
    path = Path(path)
    if len(os.fsencode(path)) > MAX_SOCKET_PATH:
        raise OSError(
            errno.ENAMETOOLONG,
            f"the I2C bridge's socket path {path} is longer than a Unix socket allows "
            f"({MAX_SOCKET_PATH} bytes)",
        )
    bridge = I2CBridgeServer(path, i2c)
    server = await asyncio.start_unix_server(bridge.handle, path=str(path))
    try:
        yield bridge
    finally:
        server.close()
        await bridge.hang_up()
        await server.wait_closed()
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


#: The prefix of the private directory of a swarm's bridge sockets, under the temporary directory
#: as the dbus-daemons' are: a Unix socket's path holds 107 bytes, which a user's DIR may exceed.
SOCKET_DIR_PREFIX = "fake-i2c-"


class RobotBridges:
    """The I2C bridges of a served swarm whose robots carry ``sensors``: one socket per robot
    carrying a force or light sensor, in a private directory removed on exit (an async context
    manager). Robots with only the Thymio's sensors need none: then nothing is served."""

    def __init__(self, sensors: Sequence[str]) -> None:
        self.force, self.light = served_parts(sensors)
        #: whether the robots carry any I2C part
        self.needed = self.force is not None or bool(self.light)
        self.directory: Path | None = None
        self._stack = contextlib.AsyncExitStack()

    async def __aenter__(self) -> RobotBridges:
        if self.needed:
            temporary = tempfile.TemporaryDirectory(prefix=SOCKET_DIR_PREFIX)
            self.directory = Path(self._stack.enter_context(temporary))
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self._stack.aclose()

    async def serve_world(self, robot_id: str, world: World, index: int) -> dict[str, Any]:
        """Serve robot ``index`` of ``world`` (:func:`world_chips`) as ``robot_id``; its agent's
        ``body`` keys (:meth:`body`)."""
        if not self.needed:
            return {}
        return await self._serve(robot_id, world_chips(world, index, self.force, self.light))

    async def serve_constant(self, robot_id: str, light: float) -> dict[str, Any]:
        """Serve ``robot_id``'s chips reading an unloaded blade and ``light`` everywhere; its
        agent's ``body`` keys (:meth:`body`)."""
        if not self.needed:
            return {}
        chips = constant_chips(self.force, self.light, light_value=light)
        return await self._serve(robot_id, chips)

    async def _serve(self, robot_id: str, chips: RobotChips) -> dict[str, Any]:
        assert self.directory is not None, "serve inside the context"
        path = self.directory / f"{robot_id}.sock"
        await self._stack.enter_async_context(serve_i2c_bridge(path, chips.i2c))
        return self.body(path)

    def body(self, path: Path) -> dict[str, Any]:
        """An agent configuration's ``body`` keys (plain data) for the bridge at ``path``: the
        socket, and the force and light parts wired as the served chips are."""
        parts: dict[str, Any] = {"i2c_bridge": str(path)}
        if self.force is not None:
            parts["force"] = msgspec.to_builtins(self.force)
        if self.light:
            parts["light"] = msgspec.to_builtins(list(self.light))
        return parts

    def readings(self, backend: str) -> str:
        """What the chips read on ``backend`` (``sim`` or ``playground``), for a person."""
        if backend == "playground":
            said = []
            if self.force is not None:
                said.append("Enki has no blade: the force sensors read an unloaded blade (0)")
            if self.light:
                said.append("it has no lamp: the light sensors read the uniform light")
            return "the I2C chips do not follow Playground: " + "; ".join(said)
        said = ["the force on each robot's blade"] if self.force is not None else []
        if self.light:
            said.append("the light at its light sensors")
        return "the I2C chips read the world: " + " and ".join(said)
