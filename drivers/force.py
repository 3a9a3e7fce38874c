"""The blade's force sensor read through an ADS1115 ADC over I2C (docs/sensors.md).

Each reading is one single-shot conversion: write the config register with the OS bit set, wait
the conversion time, poll the OS bit (bounded), read the conversion register. The ADS1115 sends
its 16-bit registers high byte first while SMBus words are low byte first, hence :func:`swap16`
on every word. The zero offset is measured at ``open()``; the reading is
``clip(sign * (raw - zero) / full_scale_counts, 0, 1)``.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from drivers.config import ADS1115_INPUTS, ADS1115_RANGES, ForceSensorConfig
from drivers.i2c import TRANSACTION_TIMEOUT, I2CDevice, SMBusLike, swap16
from minimize_surprise.errors import HardwareError
from minimize_surprise.sensors import FORCE_SENSORS

REG_CONVERSION = 0x00
REG_CONFIG = 0x01
OS_BIT = 0x8000  # write: start a single conversion; read: 1 = idle (conversion done)
MODE_SINGLE_SHOT = 0x0100
COMPARATOR_OFF = 0x0003  # COMP_QUE = 11: comparator disabled, ALERT/RDY high impedance
DATA_RATES: tuple[int, ...] = (8, 16, 32, 64, 128, 250, 475, 860)
#: Polls of the OS bit after the nominal conversion time before giving up.
MAX_POLLS = 10
#: The internal oscillator may run 10 % slow (datasheet), and waking up adds about 25 µs.
CONVERSION_MARGIN = 1.1
WAKE_UP = 0.0001


def config_word(config: ForceSensorConfig) -> int:
    """The config register value that starts one single-shot conversion for ``config``."""
    mux = ADS1115_INPUTS.index(config.inputs)
    pga = ADS1115_RANGES.index(config.pga_range_volts)
    rate = DATA_RATES.index(config.data_rate)
    return OS_BIT | mux << 12 | pga << 9 | MODE_SINGLE_SHOT | rate << 5 | COMPARATOR_OFF


def to_signed16(word: int) -> int:
    """Interpret a 16-bit word as two's complement."""
    return word - 0x10000 if word & 0x8000 else word


class ForceSensor:
    """An ADS1115 reading the force bridge, as a body part reporting ``force``.

    ``sleep`` is the blocking wait used on the bus's worker thread while a conversion runs
    (injectable so that tests can count or skip it).
    """

    sensors: tuple[str, ...] = FORCE_SENSORS

    def __init__(
        self,
        device: I2CDevice,
        config: ForceSensorConfig,
        *,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.device = device
        self.config = config
        self._sleep = sleep
        self._config_word = config_word(config)
        self._conversion_time = CONVERSION_MARGIN / config.data_rate + WAKE_UP
        # One count is range / 2**15 volts (the register spans -range .. +range).
        self.full_scale_counts = config.full_scale_volts / config.pga_range_volts * 32768.0
        self._sign = -1.0 if config.invert else 1.0
        self._timeout = TRANSACTION_TIMEOUT + self._conversion_time * (1 + MAX_POLLS)
        self.zero: float | None = None

    async def open(self) -> None:
        """Open the bus and measure the zero offset (the blade must be unloaded)."""
        if self.zero is not None:
            return
        await self.device.open()
        try:
            samples = [await self.read_raw() for _ in range(self.config.zero_samples)]
        except BaseException:
            await self.device.close()
            raise
        self.zero = float(np.mean(samples))

    def _convert(self, smbus: SMBusLike) -> int:
        address = self.device.address
        smbus.write_word_data(address, REG_CONFIG, swap16(self._config_word))
        self._sleep(self._conversion_time)
        for _ in range(MAX_POLLS):
            if swap16(smbus.read_word_data(address, REG_CONFIG)) & OS_BIT:
                return to_signed16(swap16(smbus.read_word_data(address, REG_CONVERSION)))
            self._sleep(self._conversion_time / 4)
        raise HardwareError(
            f"force: the ADS1115 at {self.device} did not finish a conversion "
            f"({MAX_POLLS} polls after {self._conversion_time * 1000:.1f} ms)"
        )

    async def read_raw(self) -> int:
        """One conversion as a signed count (-32768..32767)."""
        return await self.device.run("convert", self._convert, self._timeout)

    async def read(self) -> np.ndarray:
        """One value: the force normalised to [0, 1]."""
        if self.zero is None:
            raise HardwareError("force: the sensor is not open")
        raw = await self.read_raw()
        value = self._sign * (raw - self.zero) / self.full_scale_counts
        return np.array([min(max(value, 0.0), 1.0)])

    async def close(self) -> None:
        """Release the bus (single-shot mode leaves the ADC powered down). Never raises."""
        if self.zero is None:
            return
        self.zero = None
        await self.device.close()
