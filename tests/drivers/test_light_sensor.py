"""TSL45315 driver against the emulated chip, directly and behind a TCA9548A."""

from __future__ import annotations

import asyncio
import threading

import numpy as np
import pytest

from drivers.config import LightSensorConfig, MuxConfig
from drivers.i2c import I2CBuses, I2CDevice
from drivers.light import LightSensor
from minimize_surprise.errors import HardwareError
from standins.fake_i2c import FakeI2C, FakeSMBus, FakeTCA9548A, FakeTSL45315


def _sensor(i2c: FakeI2C, config: LightSensorConfig, name: str = "light.0", buses=None):
    buses = buses or I2CBuses(i2c.smbus)
    device = I2CDevice(buses.get(config.bus), config.address, config.mux)
    return LightSensor(device, config, name)


@pytest.mark.parametrize(("ms", "code"), [(400, 0x00), (200, 0x01), (100, 0x02)])
async def test_open_powers_on_and_sets_the_integration_time(i2c: FakeI2C, ms: int, code: int):
    chip = i2c.bus(1).attach(0x29, FakeTSL45315(lux=100))
    sensor = _sensor(i2c, LightSensorConfig(integration_ms=ms))
    await sensor.open()
    assert chip.powered and chip.registers[chip.CONFIG] == code and chip.integration_ms == ms
    await sensor.close()
    assert not chip.powered
    assert all(handle.closed for handle in i2c.handles)


@pytest.mark.parametrize(
    ("ms", "lux", "expected"),
    [(400, 301.0, 301.0), (200, 301.0, 300.0), (100, 301.0, 300.0), (100, 300_000.0, 65535 * 4)],
)
async def test_lux_uses_the_multiplier(i2c: FakeI2C, ms: int, lux: float, expected: float):
    i2c.bus(1).attach(0x29, FakeTSL45315(lux=lux))
    sensor = _sensor(i2c, LightSensorConfig(integration_ms=ms))
    await sensor.open()
    try:
        assert await sensor.read_lux() == expected
    finally:
        await sensor.close()


@pytest.mark.parametrize(("lux", "value"), [(0.0, 0.0), (256.0, 0.25), (1024.0, 1.0), (5000, 1.0)])
async def test_reading_is_normalised_by_max_lux_and_clipped(i2c: FakeI2C, lux: float, value: float):
    i2c.bus(1).attach(0x29, FakeTSL45315(lux=lux))
    sensor = _sensor(i2c, LightSensorConfig(integration_ms=400, max_lux=1024))
    await sensor.open()
    try:
        reading = await sensor.read()
    finally:
        await sensor.close()
    assert reading.shape == (1,)
    assert reading[0] == pytest.approx(value)


async def test_wrong_part_number_is_refused(i2c: FakeI2C):
    i2c.bus(1).attach(0x29, FakeTSL45315(ident=0x50))
    sensor = _sensor(i2c, LightSensorConfig())
    with pytest.raises(HardwareError, match=r"not a TSL45315 \(ID register 0x50"):
        await sensor.open()
    assert all(handle.closed for handle in i2c.handles)  # the bus was released again


async def test_missing_device_is_a_hardware_error(i2c: FakeI2C):
    i2c.bus(1)
    with pytest.raises(HardwareError, match="Remote I/O error"):
        await _sensor(i2c, LightSensorConfig()).open()


async def test_missing_bus_is_a_hardware_error(i2c: FakeI2C):
    with pytest.raises(HardwareError, match="/dev/i2c-3"):
        await _sensor(i2c, LightSensorConfig(bus=3)).open()


async def test_two_sensors_on_two_buses(i2c: FakeI2C):
    i2c.bus(1).attach(0x29, FakeTSL45315(lux=100))
    i2c.bus(3).attach(0x29, FakeTSL45315(lux=800))  # a software bus from i2c-gpio
    buses = I2CBuses(i2c.smbus)
    first = _sensor(i2c, LightSensorConfig(bus=1, integration_ms=400), "light.0", buses)
    second = _sensor(i2c, LightSensorConfig(bus=3, integration_ms=400), "light.1", buses)
    await asyncio.gather(first.open(), second.open())
    try:
        assert (await first.read_lux(), await second.read_lux()) == (100.0, 800.0)
    finally:
        await asyncio.gather(first.close(), second.close())


async def test_mux_channel_is_selected_before_every_transaction(i2c: FakeI2C):
    bus = i2c.bus(1)
    mux = bus.attach(0x70, FakeTCA9548A())
    mux.attach(0, 0x29, FakeTSL45315(lux=100))
    mux.attach(3, 0x29, FakeTSL45315(lux=800))
    buses = I2CBuses(i2c.smbus)
    config = {"integration_ms": 400}
    first = _sensor(i2c, LightSensorConfig(mux=MuxConfig(channel=0), **config), "light.0", buses)
    second = _sensor(i2c, LightSensorConfig(mux=MuxConfig(channel=3), **config), "light.1", buses)
    await first.open()
    await second.open()
    try:
        for _ in range(3):
            assert await first.read_lux() == 100.0
            assert await second.read_lux() == 800.0
    finally:
        await first.close()
        await second.close()
    # One selection per transaction (open, three reads, close), none cached.
    assert mux.selections == [0x01, 0x08] + [0x01, 0x08] * 3 + [0x01, 0x08]
    assert bus.transfers[0] == (0x70, "w", b"\x01")


async def test_sensors_behind_one_mux_never_interleave(i2c: FakeI2C):
    # Interleaved transactions would read one sensor through another's channel: wrong values.
    bus = i2c.bus(1)
    mux = bus.attach(0x70, FakeTCA9548A())
    for channel, lux in ((0, 100), (1, 200), (2, 400)):
        mux.attach(channel, 0x29, FakeTSL45315(lux=lux))
    threads: set[int] = set()

    class Watching(FakeSMBus):
        def write_byte(self, i2c_addr: int, value: int, force=None) -> None:
            threads.add(threading.get_ident())
            super().write_byte(i2c_addr, value)

    buses = I2CBuses(lambda number: Watching(i2c.bus(number)))
    sensors = [
        _sensor(
            i2c, LightSensorConfig(mux=MuxConfig(channel=c), integration_ms=400), f"s{c}", buses
        )
        for c in range(3)
    ]
    await asyncio.gather(*(s.open() for s in sensors))
    try:
        # The three at once, thirty times: each read within its timeout (0.2 s), which ninety
        # reads queued at once for the one worker could overrun on a loaded machine.
        rounds = []
        for _ in range(30):
            rounds += await asyncio.gather(*(s.read_lux() for s in sensors))
    finally:
        await asyncio.gather(*(s.close() for s in sensors))
    assert rounds == [100.0, 200.0, 400.0] * 30
    assert len(threads) == 1 and threading.get_ident() not in threads  # one worker, not the loop


async def test_read_before_open_is_a_hardware_error(i2c: FakeI2C):
    i2c.bus(1).attach(0x29, FakeTSL45315())
    with pytest.raises(HardwareError, match="not open"):
        await _sensor(i2c, LightSensorConfig()).read()


async def test_values_are_finite_floats(i2c: FakeI2C):
    i2c.bus(1).attach(0x29, FakeTSL45315(lux=lambda: 333.0))
    sensor = _sensor(i2c, LightSensorConfig(integration_ms=400, max_lux=1000))
    await sensor.open()
    try:
        reading = await sensor.read()
    finally:
        await sensor.close()
    assert reading.dtype == np.float64 and np.isfinite(reading).all()
    assert reading[0] == pytest.approx(0.333)
