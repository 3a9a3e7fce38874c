"""The I2C bridge: the real force and light drivers reading emulated chips served on a Unix
socket (drivers/i2c_bridge.py, standins/i2c_bridge.py), as a rehearsal's agent reads them.

Values round-trip through the drivers within the chips' resolution; a bus the bridge lacks, a
missing, dead or stalled server are each a HardwareError naming the socket within the bridge's
timeout (an agent whose bridge dies: tests/agent/test_agent_lost_bridge.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import time
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np
import pytest

from drivers.compose import build_body
from drivers.config import BodyConfig, ThymioConfig
from drivers.force import ForceSensor
from drivers.i2c import I2CBuses, I2CDevice
from drivers.i2c_bridge import (
    BRIDGE_CALL_TIMEOUT,
    BridgeReply,
    BridgeRequest,
    BridgeSMBus,
    bridge_factory,
    frame,
)
from drivers.light import LightSensor
from minimize_surprise.errors import HardwareError
from minimize_surprise.sensors import FORCE_SENSORS, GROUND_SENSORS, IR_SENSORS, LIGHT_SENSORS
from simulator.scenarios import scenario_config
from simulator.world import World
from standins.fake_medulla import StaticThymioModel, serve_fake_medulla
from standins.i2c_bridge import (
    SERVED_FORCE,
    SERVED_LIGHT,
    RobotChips,
    serve_i2c_bridge,
    served_parts,
    world_chips,
)

#: One count of the served ADS1115 in normalised force: full scale is 86 mV of a ±256 mV range.
FORCE_RESOLUTION = 1 / (SERVED_FORCE.full_scale_volts / SERVED_FORCE.pga_range_volts * 32768)
#: One count of a TSL45315 at 100 ms is 4 lux, of 1024 lux full scale.
LIGHT_RESOLUTION = 4 / SERVED_LIGHT[0].max_lux
#: How late a failure may come beyond the bridge's own timeout (scheduling on a loaded machine).
LATE = 0.3


class Values:
    """What the chips read: settable by the test."""

    def __init__(self) -> None:
        self.force = 0.0
        self.light = [0.0, 0.0]


@pytest.fixture
def socket_path(tmp_path: Path) -> Path:
    return tmp_path / "robot.sock"


@contextlib.asynccontextmanager
async def sensors(path: Path) -> AsyncIterator[tuple[ForceSensor, list[LightSensor]]]:
    """The real drivers, wired as a served robot, on buses of the bridge at ``path``."""
    buses = I2CBuses(bridge_factory(str(path)))
    force = ForceSensor(I2CDevice(buses.get(1), 0x48), SERVED_FORCE)
    lights = [
        LightSensor(I2CDevice(buses.get(1), c.address, c.mux), c, name)
        for c, name in zip(SERVED_LIGHT, LIGHT_SENSORS, strict=True)
    ]
    await force.open()
    for light in lights:
        await light.open()
    try:
        yield force, lights
    finally:
        for light in lights:
            await light.close()
        await force.close()


@contextlib.asynccontextmanager
async def sensors_of_a_server(
    path: Path, chips: RobotChips
) -> AsyncIterator[tuple[contextlib.AsyncExitStack, tuple[ForceSensor, list[LightSensor]]]]:
    """The bridge's server (on a stack of its own, for the test to end) and the drivers."""
    async with contextlib.AsyncExitStack() as server:
        await server.enter_async_context(serve_i2c_bridge(path, chips.i2c))
        async with sensors(path) as parts:  # closing never raises, though the bus may be gone
            yield server, parts


def test_the_messages_bytes_are_fixed():
    # Both sides of a rehearsal may run different checkouts: these bytes are the protocol.
    request = frame(BridgeRequest("read_word_data", 1, 0x48, 0x01))
    assert request == bytes.fromhex("00000014") + b"\x95\xaeread_word_data\x01\x48\x01\x00"
    assert frame(BridgeReply(value=0x1234)) == bytes.fromhex("00000006 93 cd1234 00 a0")
    failed = frame(BridgeReply(errno=121, message="Remote I/O error"))
    assert failed == bytes.fromhex("00000014 93 00 79 b0") + b"Remote I/O error"


async def test_values_round_trip_through_the_real_drivers(socket_path: Path):
    values = Values()
    force, light = served_parts(IR_SENSORS + GROUND_SENSORS + FORCE_SENSORS + LIGHT_SENSORS)
    chips = RobotChips(force, light, lambda: values.force, lambda i: values.light[i])
    async with serve_i2c_bridge(socket_path, chips.i2c) as server, sensors(socket_path) as parts:
        force_sensor, lights = parts
        assert force_sensor.zero == 0.0  # the blade was unloaded at open
        for value in np.linspace(0.0, 1.0, 23):
            values.force = float(value)
            values.light = [float(value), float(1.0 - value)]
            (read,) = await force_sensor.read()
            assert abs(read - value) <= FORCE_RESOLUTION
            for light_sensor, expected in zip(lights, values.light, strict=True):
                (lux,) = await light_sensor.read()
                assert -LIGHT_RESOLUTION < lux - expected <= 0  # the chip counts down
        assert server.requests > 0


async def test_a_robot_reads_the_worlds_force_and_light(socket_path: Path):
    world = World(scenario_config("gradient", {"robots": 2}), seed=3)
    world.set_pose(1, 0.3, -0.2, 1.0)  # away from the lamp: another light than robot 0's
    force, light = served_parts(world.sensors)
    assert force == SERVED_FORCE and light == SERVED_LIGHT
    chips = world_chips(world, 1, force, light)
    async with serve_i2c_bridge(socket_path, chips.i2c), sensors(socket_path) as parts:
        force_sensor, lights = parts
        forces = world.kernel_state[2]
        forces[1] = 0.37  # as if the blade pushed a box in the last step
        world.advance_to(world.steps)  # the sensors of this step are computed anew
        expected = world.sensor_values(1)
        (read,) = await force_sensor.read()
        assert abs(read - expected[world.sensors.index("force")]) <= FORCE_RESOLUTION
        assert abs(read - 0.37) < 0.05  # the world's own noise on top
        for light_sensor, name in zip(lights, LIGHT_SENSORS, strict=True):
            (lux,) = await light_sensor.read()
            assert abs(lux - expected[world.sensors.index(name)]) <= LIGHT_RESOLUTION


async def test_the_body_reads_the_bridge_its_configuration_names(
    socket_path: Path, dbus_address: str
):
    values = Values()
    values.light = [0.25, 0.5]
    chips = RobotChips(SERVED_FORCE, SERVED_LIGHT, lambda: values.force, lambda i: values.light[i])
    model = StaticThymioModel(prox=[0] * 7, reflected=[400, 400])
    config = BodyConfig(
        thymio=ThymioConfig(bus=dbus_address),
        force=SERVED_FORCE,
        light=list(SERVED_LIGHT),
        i2c_bridge=str(socket_path),
    )
    async with serve_i2c_bridge(socket_path, chips.i2c), serve_fake_medulla(dbus_address, model):
        body = build_body(config)
        async with body:
            values.force = 0.5
            frame_ = await body.read()
    assert body.sensors[-3:] == ("force", "light.0", "light.1")
    np.testing.assert_allclose(frame_.values[-3:], [0.5, 0.25, 0.5], atol=LIGHT_RESOLUTION)


async def test_a_bus_the_bridge_does_not_have_is_refused_at_open(socket_path: Path):
    chips = RobotChips(SERVED_FORCE, (), lambda: 0.0, lambda _: 0.0)
    async with serve_i2c_bridge(socket_path, chips.i2c):
        buses = I2CBuses(bridge_factory(str(socket_path)))
        with pytest.raises(HardwareError, match=r"open /dev/i2c-3 failed.*/dev/i2c-3") as info:
            await buses.get(3).acquire()
    assert str(socket_path) in str(info.value)


async def test_no_server_is_a_hardware_error_naming_the_socket(socket_path: Path):
    force = ForceSensor(I2CDevice(I2CBuses(bridge_factory(str(socket_path))).get(1), 0x48),
                        SERVED_FORCE)  # fmt: skip
    with pytest.raises(HardwareError, match="No such file") as info:
        await force.open()
    assert f"I2C bridge {socket_path}" in str(info.value)


async def test_a_dead_server_fails_a_read_at_once_naming_the_socket(socket_path: Path):
    chips = RobotChips(SERVED_FORCE, SERVED_LIGHT, lambda: 0.2, lambda _: 0.5)
    async with sensors_of_a_server(socket_path, chips) as (server, parts):
        force_sensor, lights = parts
        await force_sensor.read()
        await server.aclose()  # the server goes, as when surprise-sim-robots is killed
        for part in (force_sensor, *lights):
            start = time.monotonic()
            with pytest.raises(HardwareError) as info:
                await part.read()
            assert time.monotonic() - start < BRIDGE_CALL_TIMEOUT + LATE
            assert f"I2C bridge {socket_path}" in str(info.value)


async def test_a_stalled_server_is_a_hardware_error_within_the_timeout(socket_path: Path):
    # A server that accepts the connection and never answers (a stopped process).
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(socket_path))
    listener.listen()
    try:
        start = time.monotonic()
        with pytest.raises(OSError, match="no answer within") as info:
            await asyncio.to_thread(BridgeSMBus, str(socket_path), 1)
        elapsed = time.monotonic() - start
        assert isinstance(info.value, HardwareError)
        assert BRIDGE_CALL_TIMEOUT <= elapsed < BRIDGE_CALL_TIMEOUT + LATE
        assert str(socket_path) in str(info.value)
    finally:
        listener.close()


async def test_a_nack_a_bad_argument_and_garbage(socket_path: Path):
    chips = RobotChips(SERVED_FORCE, (), lambda: 0.0, lambda _: 0.0)
    async with serve_i2c_bridge(socket_path, chips.i2c):

        def client() -> None:
            bus = BridgeSMBus(str(socket_path), 1)
            # Nobody at 0x33: errno 121 as from /dev/i2c-1, and the next call works.
            with pytest.raises(OSError, match="Remote I/O error") as nack:
                bus.read_byte_data(0x33, 0)
            assert nack.value.errno == 121 and str(socket_path) in str(nack.value)
            with pytest.raises(ValueError, match="out of range"):
                bus.write_byte_data(0x48, 1, 256)  # refused before it is sent
            assert bus.read_word_data(0x48, 1) > 0  # the ADS1115's config register
            bus.close()
            with pytest.raises(OSError, match="closed"):
                bus.read_word_data(0x48, 1)
            # Not the protocol: the server hangs up rather than guess at an answer.
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as raw:
                raw.settimeout(1.0)
                raw.connect(str(socket_path))
                raw.sendall(b"\x00\x00\x00\x05hello")
                assert raw.recv(16) == b""

        await asyncio.to_thread(client)
