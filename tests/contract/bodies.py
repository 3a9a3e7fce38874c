"""The bodies the contract suite runs against.

A factory takes an ``AsyncExitStack`` (for whatever the body needs running: a bus, a fake
service, a world; everything entered there is torn down after the test) and returns a
:class:`BodyUnderTest`: the body, not yet opened, and a way to observe the motors from the
backend's side. To run the contract against another body, write its factory and add it to
:data:`FACTORIES`.
"""

from __future__ import annotations

import itertools
from collections.abc import Awaitable, Callable
from contextlib import AsyncExitStack
from dataclasses import dataclass

from drivers.body import Body
from drivers.compose import RobotBody, build_body
from drivers.config import (
    BodyConfig,
    ForceSensorConfig,
    LightSensorConfig,
    MuxConfig,
    ThymioConfig,
)
from simulator.body import SimSwarm
from simulator.scenarios import scenario_config
from simulator.world import World
from standins.fake_i2c import FakeADS1115, FakeI2C, FakeTCA9548A, FakeTSL45315
from standins.fake_medulla import StaticThymioModel, private_bus, serve_fake_medulla

#: The fake medulla answers in about a millisecond; this only bounds a broken test.
CALL_TIMEOUT = 1.0


@dataclass
class BodyUnderTest:
    """A body and how to see what its motors were last told, normalised to [-1, 1].

    ``observe_motors`` must reflect every ``drive``/``stop`` that returned before it was called,
    also after the body was closed.
    """

    body: Body
    observe_motors: Callable[[], Awaitable[tuple[float, float]]]


BodyFactory = Callable[[AsyncExitStack], Awaitable[BodyUnderTest]]


async def _robot(stack: AsyncExitStack, config: BodyConfig, i2c: FakeI2C) -> BodyUnderTest:
    """A RobotBody over the fake medulla (config.thymio.bus is replaced) and emulated I2C."""
    address = await stack.enter_async_context(private_bus())
    # Raw values beyond the sensors' ranges check that the body clips.
    model = StaticThymioModel(
        prox=[0, 1300, 2600, 4000, 4500, 5200, 32767], reflected=[900, 1100], delta=[-5, 20]
    )
    await stack.enter_async_context(serve_fake_medulla(address, model))
    thymio = ThymioConfig(bus=address, timeout=CALL_TIMEOUT, speed_scale=315)
    body = build_body(
        BodyConfig(thymio=thymio, light=config.light, force=config.force), smbus_factory=i2c.smbus
    )
    stack.push_async_callback(body.close)  # before the medulla and the bus go away

    async def observe_motors() -> tuple[float, float]:
        assert isinstance(body, RobotBody)
        if body.thymio.is_open:
            await body.thymio.is_connected()  # barrier: medulla has processed earlier writes
        return model.targets["left"] / 315, model.targets["right"] / 315

    return BodyUnderTest(body, observe_motors)


async def robot_full(stack: AsyncExitStack) -> BodyUnderTest:
    """Thymio, force sensor and two light sensors behind one multiplexer, all emulated."""
    i2c = FakeI2C()
    bus = i2c.bus(1)
    mux = bus.attach(0x70, FakeTCA9548A())
    mux.attach(0, 0x29, FakeTSL45315(lux=300.0))
    mux.attach(1, 0x29, FakeTSL45315(lux=itertools.cycle([0.0, 800.0, 9000.0]).__next__))
    # Zero samples, then a push, an overload and a pull (which must clip to 0).
    volts = itertools.chain([0.01] * 4, itertools.cycle([0.05, 0.3, -0.2]))
    bus.attach(0x48, FakeADS1115(voltage=lambda inputs: next(volts)))
    config = BodyConfig(
        light=[
            LightSensorConfig(mux=MuxConfig(channel=0), integration_ms=400),
            LightSensorConfig(mux=MuxConfig(channel=1), integration_ms=100),
        ],
        force=ForceSensorConfig(data_rate=860, zero_samples=4),
    )
    return await _robot(stack, config, i2c)


async def robot_thymio_only(stack: AsyncExitStack) -> BodyUnderTest:
    """A bare Thymio: IR and ground sensors only."""
    return await _robot(stack, BodyConfig(), FakeI2C())


#: Every body the contract covers.
async def _simulated(stack: AsyncExitStack, scenario: str, *, realtime: bool) -> BodyUnderTest:
    """Robot 1 of a simulated world; the other robots stand still and take no part."""
    world = World(scenario_config(scenario), seed=4)
    swarm = SimSwarm(world, realtime=realtime)
    if realtime:
        await stack.enter_async_context(swarm)
    body = swarm.body(1)
    stack.push_async_callback(body.close)

    async def observe_motors() -> tuple[float, float]:
        left, right = world.commands[1]
        return float(left), float(right)

    return BodyUnderTest(body, observe_motors)


async def sim_lockstep_all_sensors(stack: AsyncExitStack) -> BodyUnderTest:
    """A simulated Thymio with blade, force and light sensors, in lockstep."""
    return await _simulated(stack, "gradient", realtime=False)


async def sim_realtime_basic(stack: AsyncExitStack) -> BodyUnderTest:
    """A simulated basic Thymio in a world paced at 10 Hz of wall-clock time."""
    return await _simulated(stack, "basic", realtime=True)


FACTORIES: list[BodyFactory] = [
    robot_full,
    robot_thymio_only,
    sim_lockstep_all_sensors,
    sim_realtime_basic,
]
