"""The emulated I2C devices behave like the chips on the wire (so driver tests mean something)."""

from __future__ import annotations

import errno

import pytest

from standins.fake_i2c import FakeADS1115, FakeI2C, FakeTCA9548A, FakeTSL45315


def test_unknown_address_nacks_with_remote_io_error(i2c: FakeI2C):
    i2c.bus(1)
    with pytest.raises(OSError) as info:
        i2c.smbus(1).read_byte_data(0x29, 0x8A)
    assert info.value.errno == errno.EREMOTEIO == 121


def test_unknown_bus_does_not_exist(i2c: FakeI2C):
    with pytest.raises(FileNotFoundError):
        i2c.smbus(7)


def test_closed_handle_and_out_of_range_values(i2c: FakeI2C):
    i2c.bus(1).attach(0x29, FakeTSL45315())
    with i2c.smbus(1) as smbus, pytest.raises(ValueError):
        smbus.write_byte_data(0x29, 0x80, 256)
    with pytest.raises(OSError) as info:
        smbus.read_byte_data(0x29, 0x8A)
    assert info.value.errno == errno.EBADF


def test_tsl45315_registers(i2c: FakeI2C):
    chip = i2c.bus(1).attach(0x29, FakeTSL45315(lux=1000.0))
    smbus = i2c.smbus(1)
    assert smbus.read_byte_data(0x29, 0x8A) == 0xA0
    assert smbus.read_word_data(0x29, 0x84) == 0  # powered down: no conversion yet
    smbus.write_byte_data(0x29, 0x80, 0x03)
    smbus.write_byte_data(0x29, 0x81, 0x02)
    assert chip.powered and chip.integration_ms == 100
    assert smbus.read_word_data(0x29, 0x84) == 250  # low byte first, as the chip sends it
    assert smbus.read_i2c_block_data(0x29, 0x84, 2) == [250, 0]
    with pytest.raises(OSError):
        smbus.read_byte_data(0x29, 0x0A)  # no command bit


def test_mux_routes_to_the_selected_channel_only(i2c: FakeI2C):
    bus = i2c.bus(1)
    mux = bus.attach(0x70, FakeTCA9548A())
    mux.attach(2, 0x29, FakeTSL45315(ident=0xA2))
    mux.attach(6, 0x29, FakeTSL45315(ident=0xA6))
    smbus = i2c.smbus(1)
    with pytest.raises(OSError) as info:
        smbus.read_byte_data(0x29, 0x8A)  # nothing selected: a NACK
    assert info.value.errno == errno.EREMOTEIO
    smbus.write_byte(0x70, 1 << 6)
    assert smbus.read_byte_data(0x29, 0x8A) == 0xA6
    assert smbus.read_byte(0x70) == 1 << 6
    smbus.write_byte(0x70, 1 << 2)
    assert smbus.read_byte_data(0x29, 0x8A) == 0xA2
    smbus.write_byte(0x70, 1 << 2 | 1 << 6)
    with pytest.raises(OSError) as info:
        smbus.read_byte_data(0x29, 0x8A)  # two devices answer at once
    assert info.value.errno == errno.EIO


def test_ads1115_registers_are_big_endian_on_the_wire(i2c: FakeI2C):
    ads = i2c.bus(1).attach(0x48, FakeADS1115(voltage=0.1, busy_reads=2))
    smbus = i2c.smbus(1)
    # Power-on default config 0x8583, which read_word_data returns byte-swapped.
    assert smbus.read_word_data(0x48, 0x01) == 0x8385
    # Start a single-shot conversion at ±0.256 V: 0x8B83 goes on the wire as 8B 83.
    smbus.write_i2c_block_data(0x48, 0x01, [0x8B, 0x83])
    assert ads.conversions == 1 and ads.range_volts == 0.256
    assert smbus.read_word_data(0x48, 0x01) & 0x80 == 0  # OS bit (wire byte 0, bit 7): busy
    assert smbus.read_word_data(0x48, 0x00) == 0  # not finished: the old result
    assert smbus.read_word_data(0x48, 0x01) & 0x80 == 0
    assert smbus.read_word_data(0x48, 0x01) & 0x80 == 0x80  # done
    assert smbus.read_word_data(0x48, 0x00) == 0x0032  # 12800 = 0x3200, swapped
    smbus.write_word_data(0x48, 0x02, 0x3412)  # Lo_thresh 0x1234 sent as 12 34
    assert smbus.read_i2c_block_data(0x48, 0x02, 2) == [0x12, 0x34]


def test_ads1115_continuous_mode_converts_on_every_read(i2c: FakeI2C):
    ads = i2c.bus(1).attach(0x48, FakeADS1115(voltage=lambda inputs: -0.256))
    smbus = i2c.smbus(1)
    smbus.write_i2c_block_data(0x48, 0x01, [0x0A, 0x83])  # MODE=0: continuous
    assert not ads.single_shot
    assert smbus.read_i2c_block_data(0x48, 0x00, 2) == [0x80, 0x00]  # -32768
    assert ads.conversions == 1
