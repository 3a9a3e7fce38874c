"""The Thymio's top LED through the fake asebamedulla: ``leds.top`` written as three values 0..32,
recorded by the robot's model, and a robot that does not declare it (Aseba Playground's) named
at once, since this write asks medulla for its answer."""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest

from drivers.config import ThymioConfig
from drivers.thymio import LEDS_TOP, ThymioBase
from minimize_surprise.errors import DBusReplyError
from standins.fake_medulla import FakeMedulla, StaticThymioModel

ConfigFactory = Callable[..., ThymioConfig]


async def test_the_top_led_is_written_in_the_firmware_s_scale(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    medulla.native.add(LEDS_TOP)  # a real Thymio's firmware declares it
    thymio = ThymioBase(thymio_config())
    await thymio.open()
    try:
        await thymio.set_top_led(0.0, 1.0, 0.0)
        await thymio.set_top_led(0.5, -3.0, math.nan)  # clamped, NaN off: never an error
        await thymio.set_top_led(0.0, 0.0, 0.0)
    finally:
        await thymio.close()
    assert model.led_log == [[0, 32, 0], [16, 0, 0], [0, 0, 0]]
    assert model.variables[LEDS_TOP] == [0, 0, 0] and not medulla.rejected


async def test_a_robot_without_leds_top_is_named_at_once(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    # The plain fake is Aseba Playground's Thymio, which has no leds.top variable.
    thymio = ThymioBase(thymio_config())
    await thymio.open()
    try:
        with pytest.raises(DBusReplyError, match=r"has no leds\.top variable"):
            await thymio.set_top_led(0.0, 1.0, 0.0)
        await thymio.set_speeds(0.5, 0.5)  # the robot drives on as before
        await thymio.is_connected()
        assert model.targets == {"left": 132, "right": 132}
    finally:
        await thymio.close()
    assert model.led_log == []
    assert medulla.rejected == [f"SetVariable: variable {LEDS_TOP} does not exists"]
