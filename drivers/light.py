"""TSL45315 ambient light sensor over I2C (docs/sensors.md).

Every register access carries the command bit (register ``0x80 | reg``). ``open()`` checks the
part number in the ID register, powers the sensor on in continuous mode and sets the integration
time; ``read()`` returns ``lux / max_lux`` clipped to [0, 1]. The first conversion completes one
integration time after ``open()``; until then the sensor reports 0 lux.
"""

from __future__ import annotations

import logging

import numpy as np

from drivers.config import LightSensorConfig
from drivers.i2c import I2CDevice, SMBusLike
from minimize_surprise.errors import HardwareError

log = logging.getLogger(__name__)

COMMAND = 0x80
REG_CONTROL = 0x00
REG_CONFIG = 0x01
REG_DATALOW = 0x04
REG_ID = 0x0A
CONTROL_POWER_ON = 0x03  # normal operation: continuous conversions
CONTROL_POWER_DOWN = 0x00
#: Upper nibble of the ID register of a TSL45315.
PART_NUMBER = 0xA
#: Integration time in ms -> (CONFIG value, lux per count).
INTEGRATION: dict[int, tuple[int, int]] = {400: (0x00, 1), 200: (0x01, 2), 100: (0x02, 4)}


class LightSensor:
    """One TSL45315 as a body part reporting one sensor (``light.0`` or ``light.1``)."""

    def __init__(self, device: I2CDevice, config: LightSensorConfig, name: str) -> None:
        self.device = device
        self.config = config
        self.sensors: tuple[str, ...] = (name,)
        self._config_code, self._multiplier = INTEGRATION[config.integration_ms]
        self._open = False

    async def open(self) -> None:
        """Check the ID, power on, set the integration time. Raises ``HardwareError``."""
        if self._open:
            return
        await self.device.open()
        try:
            await self.device.run("power on", self._power_on)
        except BaseException:
            await self.device.close()
            raise
        self._open = True

    def _power_on(self, smbus: SMBusLike) -> None:
        address = self.device.address
        ident = smbus.read_byte_data(address, COMMAND | REG_ID)
        if ident >> 4 != PART_NUMBER:
            raise HardwareError(
                f"{self.sensors[0]}: the device at {self.device} is not a TSL45315 "
                f"(ID register 0x{ident:02X}, expected 0x{PART_NUMBER:X}_)"
            )
        smbus.write_byte_data(address, COMMAND | REG_CONTROL, CONTROL_POWER_ON)
        smbus.write_byte_data(address, COMMAND | REG_CONFIG, self._config_code)

    async def read_lux(self) -> float:
        """The illuminance in lux."""
        address = self.device.address
        # DATALOW and DATAHIGH in one word transfer, low byte first as SMBus words are.
        raw = await self.device.run(
            "read lux", lambda smbus: smbus.read_word_data(address, COMMAND | REG_DATALOW)
        )
        return float(raw * self._multiplier)

    async def read(self) -> np.ndarray:
        """One value: ``lux / max_lux`` clipped to [0, 1]."""
        lux = await self.read_lux()
        return np.array([min(max(lux / self.config.max_lux, 0.0), 1.0)])

    async def close(self) -> None:
        """Power the sensor down (best effort) and release the bus. Never raises."""
        if not self._open:
            return
        self._open = False
        address = self.device.address
        try:
            await self.device.run(
                "power down",
                lambda smbus: smbus.write_byte_data(
                    address, COMMAND | REG_CONTROL, CONTROL_POWER_DOWN
                ),
            )
        except Exception as exc:  # the sensor may be the reason we are closing
            log.warning("%s: power down failed: %s", self.sensors[0], exc)
        finally:
            await self.device.close()
