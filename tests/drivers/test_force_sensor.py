"""ADS1115 force sensor driver against the emulated ADC."""

from __future__ import annotations

import pytest

from drivers.config import ForceSensorConfig, MuxConfig
from drivers.force import MAX_POLLS, ForceSensor, config_word, to_signed16
from drivers.i2c import I2CBuses, I2CDevice, swap16
from minimize_surprise.errors import HardwareError
from standins.fake_i2c import FakeADS1115, FakeI2C, FakeTCA9548A

# Counts per volt at ±0.256 V: 32768 / 0.256.
COUNTS_PER_VOLT = 128_000.0


def _sensor(i2c: FakeI2C, config: ForceSensorConfig, sleeps: list[float] | None = None):
    device = I2CDevice(I2CBuses(i2c.smbus).get(config.bus), config.address, config.mux)
    record = sleeps.append if sleeps is not None else (lambda seconds: None)
    return ForceSensor(device, config, sleep=record)


class Voltages:
    """A voltage source: ``zero`` for the first ``n_zero`` conversions, then ``values`` in turn."""

    def __init__(self, zero: float, n_zero: int, *values: float) -> None:
        self.samples = [zero] * n_zero + list(values)
        self.inputs: list[str] = []

    def __call__(self, inputs: str) -> float:
        self.inputs.append(inputs)
        return self.samples.pop(0) if len(self.samples) > 1 else self.samples[0]


def test_config_word_matches_the_datasheet_layout():
    # OS=1 | MUX=000 (AIN0-AIN1) | PGA=101 (±0.256 V) | MODE=1 | DR=100 (128 SPS) | COMP_QUE=11
    assert config_word(ForceSensorConfig()) == 0b1_000_101_1_100_0_0_0_11 == 0x8B83
    word = config_word(ForceSensorConfig(inputs="AIN2", pga_range_volts=2.048, data_rate=860))
    assert word == 0b1_110_010_1_111_0_0_0_11


def test_helpers():
    assert swap16(0x1234) == 0x3412
    assert (
        to_signed16(0xFFFF) == -1 and to_signed16(0x8000) == -32768 and to_signed16(0x7FFF) == 32767
    )


async def test_config_goes_on_the_wire_high_byte_first(i2c: FakeI2C):
    bus = i2c.bus(1)
    bus.attach(0x48, FakeADS1115())
    sensor = _sensor(i2c, ForceSensorConfig(zero_samples=1))
    await sensor.open()
    await sensor.close()
    assert (0x48, "w", bytes([0x01, 0x8B, 0x83])) in bus.transfers


@pytest.mark.parametrize(("volts", "count"), [(0.0364, 4659), (-0.0364, -4659), (1.0, 32767)])
async def test_conversion_is_read_big_endian_and_signed(i2c: FakeI2C, volts: float, count: int):
    i2c.bus(1).attach(0x48, FakeADS1115(voltage=volts))
    sensor = _sensor(i2c, ForceSensorConfig(zero_samples=1))
    await sensor.open()
    try:
        assert await sensor.read_raw() == count
    finally:
        await sensor.close()


async def test_zero_offset_is_the_mean_at_open_and_reading_is_normalised(i2c: FakeI2C):
    # Zero at 10 mV; +43 mV above it is half of the default 86 mV full scale.
    source = Voltages(0.010, 8, 0.053, 0.010 + 0.086, 0.2, 0.0)
    ads = i2c.bus(1).attach(0x48, FakeADS1115(voltage=source))
    sensor = _sensor(i2c, ForceSensorConfig())
    await sensor.open()
    try:
        assert ads.conversions == 8
        assert sensor.zero == pytest.approx(0.010 * COUNTS_PER_VOLT)
        assert sensor.full_scale_counts == pytest.approx(0.086 * COUNTS_PER_VOLT)
        readings = [float((await sensor.read())[0]) for _ in range(4)]
    finally:
        await sensor.close()
    assert readings == pytest.approx([0.5, 1.0, 1.0, 0.0], abs=1e-3)  # clipped both ways
    assert set(source.inputs) == {"AIN0-AIN1"}


async def test_invert_flips_the_sign(i2c: FakeI2C):
    i2c.bus(1).attach(0x48, FakeADS1115(voltage=Voltages(0.0, 2, -0.043)))
    sensor = _sensor(i2c, ForceSensorConfig(zero_samples=2, invert=True))
    await sensor.open()
    try:
        assert (await sensor.read())[0] == pytest.approx(0.5, abs=1e-3)
    finally:
        await sensor.close()


async def test_inputs_gain_and_rate_reach_the_chip(i2c: FakeI2C):
    ads = i2c.bus(1).attach(0x48, FakeADS1115(voltage=0.5))
    config = ForceSensorConfig(
        inputs="AIN2-AIN3", pga_range_volts=1.024, data_rate=860, full_scale_volts=1.0
    )
    sensor = _sensor(i2c, config)
    await sensor.open()
    try:
        assert ads.inputs == "AIN2-AIN3" and ads.range_volts == 1.024 and ads.single_shot
        assert await sensor.read_raw() == 16000  # 0.5 V of ±1.024 V
    finally:
        await sensor.close()


async def test_waits_for_the_conversion_then_polls_the_os_bit(i2c: FakeI2C):
    i2c.bus(1).attach(0x48, FakeADS1115(voltage=0.01, busy_reads=3))
    sleeps: list[float] = []
    sensor = _sensor(i2c, ForceSensorConfig(zero_samples=1, data_rate=128), sleeps)
    await sensor.open()
    zero = sensor.zero
    await sensor.close()
    # The nominal conversion time (1/128 s, 10 % margin), then three short waits while busy.
    assert sleeps[0] == pytest.approx(1.1 / 128 + 0.0001)
    assert len(sleeps) == 4 and all(s < sleeps[0] for s in sleeps[1:])
    assert zero == pytest.approx(0.01 * COUNTS_PER_VOLT)


async def test_a_conversion_that_never_finishes_is_a_hardware_error(i2c: FakeI2C):
    i2c.bus(1).attach(0x48, FakeADS1115(busy_reads=10**6))
    sleeps: list[float] = []
    with pytest.raises(HardwareError, match="did not finish a conversion"):
        await _sensor(i2c, ForceSensorConfig(), sleeps).open()
    assert len(sleeps) == 1 + MAX_POLLS
    assert all(handle.closed for handle in i2c.handles)


async def test_missing_adc_is_a_hardware_error(i2c: FakeI2C):
    i2c.bus(1)
    with pytest.raises(HardwareError, match="Remote I/O error"):
        await _sensor(i2c, ForceSensorConfig(address=0x49)).open()


async def test_read_before_open_is_a_hardware_error(i2c: FakeI2C):
    i2c.bus(1).attach(0x48, FakeADS1115())
    with pytest.raises(HardwareError, match="not open"):
        await _sensor(i2c, ForceSensorConfig()).read()


async def test_behind_a_mux(i2c: FakeI2C):
    mux = i2c.bus(1).attach(0x70, FakeTCA9548A())
    mux.attach(5, 0x48, FakeADS1115(voltage=Voltages(0.0, 1, 0.086)))
    sensor = _sensor(i2c, ForceSensorConfig(zero_samples=1, mux=MuxConfig(channel=5)))
    await sensor.open()
    try:
        assert (await sensor.read())[0] == pytest.approx(1.0, abs=1e-3)
    finally:
        await sensor.close()
    assert set(mux.selections) == {1 << 5}


async def test_real_sleep_is_short_at_the_fastest_rate(i2c: FakeI2C):
    # With the default blocking sleep the wait runs on the bus thread, not on the event loop.
    i2c.bus(1).attach(0x48, FakeADS1115(voltage=0.0))
    config = ForceSensorConfig(zero_samples=2, data_rate=860)
    device = I2CDevice(I2CBuses(i2c.smbus).get(1), 0x48)
    sensor = ForceSensor(device, config)
    await sensor.open()
    try:
        assert (await sensor.read())[0] == 0.0
    finally:
        await sensor.close()
