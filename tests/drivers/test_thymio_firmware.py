"""The Thymio's firmware version through asebamedulla (``_fwversion``), for the agent's Hello:
what Aseba Playground's Thymio answers, a current firmware's, and none where the robot does not
declare the variable."""

from __future__ import annotations

from collections.abc import Callable

from drivers.config import ThymioConfig
from drivers.thymio import FWVERSION, ThymioBase
from standins.fake_medulla import PLAYGROUND_FWVERSION, FakeMedulla, StaticThymioModel

ConfigFactory = Callable[..., ThymioConfig]


async def test_the_firmware_version_is_fwversion_0(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    thymio = ThymioBase(thymio_config())
    await thymio.open()
    try:
        assert await thymio.read_firmware() == PLAYGROUND_FWVERSION[0] == 11
        model.variables[FWVERSION] = [14, 0]
        assert await thymio.read_firmware() == 14
        medulla.native.discard(FWVERSION)  # a robot that does not declare it
        assert await thymio.read_firmware() is None
    finally:
        await thymio.close()
