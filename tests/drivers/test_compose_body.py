"""build_body / RobotBody: parts in canonical order, lifecycle, failures."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable

import numpy as np
import pytest

from drivers.compose import RobotBody, build_body
from drivers.config import BodyConfig, ForceSensorConfig, LightSensorConfig, MuxConfig
from drivers.thymio import ThymioConfig
from minimize_surprise.errors import HardwareError, HardwareTimeoutError
from minimize_surprise.sensors import ALL_SENSORS
from standins.fake_i2c import FakeADS1115, FakeI2C, FakeTCA9548A, FakeTSL45315
from standins.fake_medulla import FakeMedulla, StaticThymioModel

ConfigFactory = Callable[..., ThymioConfig]


def _full(i2c: FakeI2C, thymio: ThymioConfig, light1_ident: int = 0xA0) -> RobotBody:
    """Two light sensors on two buses (0.25 and 0.5), a force sensor reading 0.5 after zero."""
    i2c.bus(1).attach(0x29, FakeTSL45315(lux=256.0))
    mux = i2c.bus(3).attach(0x71, FakeTCA9548A())
    mux.attach(4, 0x29, FakeTSL45315(lux=512.0, ident=light1_ident))
    volts = iter([0.0, 0.0] + [0.043] * 100)
    i2c.bus(1).attach(0x48, FakeADS1115(voltage=lambda inputs: next(volts)))
    config = BodyConfig(
        thymio=thymio,
        light=[
            LightSensorConfig(bus=1, integration_ms=400),
            LightSensorConfig(bus=3, mux=MuxConfig(address=0x71, channel=4), integration_ms=400),
        ],
        force=ForceSensorConfig(bus=1, zero_samples=2, data_rate=860),
    )
    return build_body(config, smbus_factory=i2c.smbus)


async def test_full_body_reads_every_part_in_canonical_order(
    medulla: FakeMedulla, i2c: FakeI2C, thymio_config: ConfigFactory
):
    body = _full(i2c, thymio_config())
    assert body.sensors == ALL_SENSORS
    async with body:
        frame = await body.read()
    expected = [0, 0.25, 0.5, 1.0, 1.0, 0, 0.2, 1.0, 0.0, 0.5, 0.25, 0.5]
    np.testing.assert_allclose(frame.values, expected, atol=1e-3)
    assert all(handle.closed for handle in i2c.handles)


async def test_thymio_only_body(medulla: FakeMedulla, thymio_config: ConfigFactory):
    body = build_body(BodyConfig(thymio=thymio_config()))
    assert body.sensors == ALL_SENSORS[:9]
    async with body:
        assert (await body.read()).values.shape == (9,)


async def test_a_part_failing_to_open_closes_everything(
    medulla: FakeMedulla, model: StaticThymioModel, i2c: FakeI2C, thymio_config: ConfigFactory
):
    body = _full(i2c, thymio_config(), light1_ident=0x30)
    with pytest.raises(HardwareError, match=r"light\.1: the device at bus 3"):
        async with body:
            pytest.fail("must not get here")
    assert not body.thymio.is_open
    assert model.target_log[-2:] == [("left", 0), ("right", 0)]
    assert all(handle.closed for handle in i2c.handles)


async def test_a_failing_part_fails_the_read(
    medulla: FakeMedulla, i2c: FakeI2C, thymio_config: ConfigFactory
):
    body = _full(i2c, thymio_config(timeout=0.25))
    async with body:
        del i2c.bus(1).devices[0x48]  # the ADC falls off the bus
        with pytest.raises(HardwareError, match="Remote I/O error"):
            await body.read()
        i2c.bus(1).attach(0x48, FakeADS1115())
        medulla.hang = True
        with pytest.raises(HardwareTimeoutError):
            await body.read()


async def test_close_stops_the_motors_first(
    medulla: FakeMedulla, model: StaticThymioModel, i2c: FakeI2C, thymio_config: ConfigFactory
):
    body = _full(i2c, thymio_config())
    seen_at_part_close: list[dict[str, int]] = []
    for part in body.parts[1:]:
        original = part.close

        async def close(original=original) -> None:
            seen_at_part_close.append(dict(model.targets))
            await original()

        part.close = close  # type: ignore[method-assign]
    async with body:
        await body.drive(1.0, 0.5)
        await body.thymio.is_connected()
        assert model.targets == {"left": 265, "right": 132}
    # The stop had reached medulla before any other part released its hardware.
    assert seen_at_part_close == [{"left": 0, "right": 0}] * 3


async def test_read_and_drive_need_an_open_body(medulla: FakeMedulla, thymio_config: ConfigFactory):
    body = build_body(BodyConfig(thymio=thymio_config()))
    with pytest.raises(HardwareError, match="not open"):
        await body.read()
    with pytest.raises(HardwareError):
        await body.drive(0.1, 0.1)


def test_parts_must_report_known_distinct_sensors():
    class Odd:
        sensors = ("ir.f0",)

    from drivers.thymio import ThymioBase

    with pytest.raises(ValueError, match="repeated"):
        RobotBody(ThymioBase(), [Odd()])  # type: ignore[list-item]


def test_importing_the_drivers_needs_neither_dbus_nor_smbus():
    code = (
        "import sys, drivers, drivers.compose, drivers.thymio, drivers.light, drivers.force;"
        "from drivers.config import BodyConfig;"
        "drivers.compose.build_body(BodyConfig());"
        "assert 'dbus_fast' not in sys.modules and 'smbus2' not in sys.modules, sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
