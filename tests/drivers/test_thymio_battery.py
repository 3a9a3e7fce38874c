"""The Thymio's battery through asebamedulla: read when the robot declares ``_vbat``, unknown
when it does not (Aseba Playground), and a robot that does not answer is never an unknown
battery."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest

from drivers.config import ThymioConfig
from drivers.thymio import VBAT, ThymioBase
from minimize_surprise.errors import HardwareTimeoutError
from standins.fake_medulla import FakeMedulla, StaticThymioModel

ConfigFactory = Callable[..., ThymioConfig]
# Long enough that a live fake medulla on a loaded CI machine always answers in time
# (0.05 s once failed an open in CI), short enough that the hang tests stay quick.
HANG_TIMEOUT = 0.25


async def test_battery_voltage_from_vbat(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    medulla.native.add(VBAT)
    model.variables[VBAT] = [800, 799]  # (800 + 799) / 397.8 = 4.0196 V
    thymio = ThymioBase(thymio_config())
    await thymio.open()
    try:
        assert await thymio.read_battery() == pytest.approx(4.020, abs=1e-3)
        model.variables[VBAT] = [700, 700]
        assert await thymio.read_battery() == pytest.approx(3.519, abs=1e-3)
    finally:
        await thymio.close()


async def test_battery_unknown_where_the_robot_does_not_declare_it(
    medulla: FakeMedulla, thymio_config: ConfigFactory
):
    thymio = ThymioBase(thymio_config())
    await thymio.open()
    try:
        start = time.monotonic()
        assert await thymio.read_battery() is None
        # medulla refuses the name itself, without asking the robot: at once.
        assert time.monotonic() - start < 0.5
    finally:
        await thymio.close()


async def test_a_robot_that_does_not_answer_is_not_an_unknown_battery(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    medulla.native.add(VBAT)
    model.variables[VBAT] = [800, 800]
    thymio = ThymioBase(thymio_config(timeout=HANG_TIMEOUT))
    await thymio.open()
    try:
        medulla.hang = True
        with pytest.raises(HardwareTimeoutError):
            await thymio.read_battery()
        medulla.hang = False
    finally:
        await thymio.close()
