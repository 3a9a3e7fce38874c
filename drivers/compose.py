"""A real robot's :class:`~drivers.body.Body`, composed from the parts its configuration names."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Sequence
from typing import Final

import numpy as np

from drivers.body import Body, PartReading, SensorFrame, describe_error
from drivers.config import BodyConfig
from drivers.force import ForceSensor
from drivers.i2c import I2CBuses, I2CDevice, SMBusFactory
from drivers.i2c_bridge import bridge_factory
from drivers.light import LightSensor
from drivers.parts import Part, gather_all
from drivers.thymio import ThymioBase
from minimize_surprise.errors import HardwareError
from minimize_surprise.sensors import ALL_SENSORS, LIGHT_SENSORS

log = logging.getLogger(__name__)

#: Seconds one part may take to answer a check: each driver bounds its own calls well below this
#: (a Thymio read waits one sensor period, an I2C transfer milliseconds); a part that takes longer
#: is reported as not answering rather than holding the check up.
PART_READ_TIMEOUT: Final = 2.0


class RobotBody(Body):
    """A Thymio base plus optional sensor parts, behind the ``Body`` interface.

    ``sensors`` lists the parts' sensors in canonical order
    (``minimize_surprise.sensors.ALL_SENSORS``). ``read()`` reads every part concurrently and stamps
    the frame with ``time.monotonic()`` when the last part answered. ``close()`` stops the motors
    before releasing anything else.
    """

    def __init__(self, thymio: ThymioBase, parts: Sequence[Part] = ()) -> None:
        self.thymio = thymio
        self.parts: tuple[Part, ...] = (thymio, *parts)
        names = [name for part in self.parts for name in part.sensors]
        if len(set(names)) != len(names) or not set(names) <= set(ALL_SENSORS):
            raise ValueError(f"parts report unknown or repeated sensors: {names}")
        self._sensors = tuple(sorted(names, key=ALL_SENSORS.index))
        # Position in the parts' concatenated output of each sensor in canonical order.
        self._order = np.array([names.index(name) for name in self._sensors])
        self._opened: list[Part] = []

    @property
    def sensors(self) -> tuple[str, ...]:
        return self._sensors

    async def open(self) -> None:
        """Open the Thymio first (so its motors can be stopped), then the other parts at once.

        If any part fails, everything opened so far is closed and the error is raised.
        """
        if self._opened:
            return
        try:
            await self.thymio.open()
            self._opened.append(self.thymio)
            others = self.parts[1:]
            results = await _settle(*(part.open() for part in others))
            self._opened.extend(p for p, r in zip(others, results, strict=True) if r is None)
            for result in results:
                if result is not None:
                    raise result
        except BaseException:
            await self.close()
            raise

    async def recover(self) -> None:
        """Open the body if it never opened; otherwise get the Thymio back (see
        :meth:`ThymioBase.recover`: a new medulla, the program loaded again)."""
        if not self._opened:
            await self.open()
        else:
            await self.thymio.recover()

    async def close(self) -> None:
        """Stop the motors, then release every part. Idempotent; never raises."""
        opened, self._opened = self._opened, []
        if self.thymio in opened:
            await self.thymio.close()  # stops the motors first, logs its own failures
        for part in opened:
            if part is not self.thymio:
                try:
                    await part.close()
                except Exception as exc:  # parts promise not to raise; keep closing the rest
                    log.warning("closing %s failed: %r", part.sensors, exc)

    async def read(self) -> SensorFrame:
        """One frame from every part, in canonical sensor order; raises ``HardwareError``."""
        if not self._opened:
            raise HardwareError("the body is not open")
        values = await gather_all(*(part.read() for part in self.parts))
        timestamp = time.monotonic()
        return SensorFrame(values=np.concatenate(values)[self._order], timestamp=timestamp)

    async def read_parts(self) -> list[PartReading]:
        """Every part read on its own and at once, each bounded by :data:`PART_READ_TIMEOUT`:
        the Thymio (``thymio``: medulla and the robot), the force sensor, each light sensor."""

        async def one(part: Part) -> PartReading:
            name = "thymio" if part is self.thymio else part.sensors[0]
            if part not in self._opened:
                return PartReading(name, part.sensors, error="not open (it failed to start)")
            try:
                async with asyncio.timeout(PART_READ_TIMEOUT):
                    values = await part.read()
            except TimeoutError:
                return PartReading(
                    name, part.sensors, error=f"no answer within {PART_READ_TIMEOUT} s"
                )
            except Exception as exc:
                return PartReading(name, part.sensors, error=describe_error(exc))
            return PartReading(name, part.sensors, tuple(float(v) for v in values))

        return list(await asyncio.gather(*(one(part) for part in self.parts)))

    async def read_battery(self) -> float | None:
        """The Thymio's battery voltage (None where medulla's robot does not declare ``_vbat``)."""
        return await self.thymio.read_battery()

    async def read_firmware(self) -> int | None:
        """The Thymio's firmware version (None where medulla's robot does not declare
        ``_fwversion``)."""
        return await self.thymio.read_firmware()

    async def drive(self, left: float, right: float) -> None:
        """Set the wheel speeds (normalised; clamped, NaN is 0)."""
        await self.thymio.set_speeds(left, right)

    async def stop(self) -> None:
        """Set both wheel speeds to zero."""
        await self.thymio.stop()

    async def set_top_led(self, red: float, green: float, blue: float) -> None:
        """The Thymio's top LED (:meth:`ThymioBase.set_top_led`)."""
        await self.thymio.set_top_led(red, green, blue)


async def _settle(*awaitables: Awaitable[None]) -> list[BaseException | None]:
    """Await all; each one's exception, or ``None`` where it succeeded."""
    results = await asyncio.gather(*awaitables, return_exceptions=True)
    return [r if isinstance(r, BaseException) else None for r in results]


def build_body(config: BodyConfig, *, smbus_factory: SMBusFactory | None = None) -> RobotBody:
    """The body described by ``config`` (nothing is opened until ``open()``/``async with``).

    ``smbus_factory(bus_number)`` opens an I2C bus; the default is ``smbus2.SMBus``, or the bridge
    at ``config.i2c_bridge`` when it names one (:mod:`drivers.i2c_bridge`), and tests pass
    ``standins.fake_i2c`` buses. Parts are reported in canonical order: the Thymio's IR and ground
    sensors, ``force``, ``light.0``, ``light.1`` (light sensors in the order of ``config.light``).
    """
    if smbus_factory is None and config.i2c_bridge is not None:
        # A rehearsal: the same drivers, their transfers answered by emulated chips elsewhere.
        smbus_factory = bridge_factory(config.i2c_bridge)
    buses = I2CBuses(smbus_factory)
    parts: list[Part] = []
    if config.force is not None:
        device = I2CDevice(buses.get(config.force.bus), config.force.address, config.force.mux)
        parts.append(ForceSensor(device, config.force))
    for name, light in zip(LIGHT_SENSORS, config.light, strict=False):
        device = I2CDevice(buses.get(light.bus), light.address, light.mux)
        parts.append(LightSensor(device, light, name))
    return RobotBody(ThymioBase(config.thymio), parts)
