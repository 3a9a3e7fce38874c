"""Emulated I2C for testing the real drivers: an SMBus handle and chips modelled on the wire.

:class:`FakeI2C` holds numbered buses; :meth:`FakeI2C.smbus` opens one and is a drop-in
``smbus_factory`` for :func:`drivers.compose.build_body`. Devices implement two transfers, like
the real chips: ``write(data)`` (a register pointer, then data bytes) and ``read(length)``.
:class:`FakeSMBus` maps the SMBus calls onto them exactly as the kernel does, so a word read
returns the first byte on the wire in its low byte: the ADS1115's big-endian registers come back
byte-swapped, as with real ``smbus2``. An address nobody answers raises ``OSError`` errno 121
(Remote I/O error), as a NACK does on Linux.

Devices: :class:`FakeTSL45315` (light), :class:`FakeTCA9548A` (multiplexer; devices behind an
unselected channel do not answer), :class:`FakeADS1115` (ADC, single-shot conversions).
"""

from __future__ import annotations

import errno
import os
import threading
from collections.abc import Callable
from typing import ClassVar, Protocol, Self, TypeVar

from drivers.config import ADS1115_INPUTS


class FakeDevice(Protocol):
    """An emulated I2C chip: what it does with one write transfer and one read transfer."""

    def write(self, data: bytes) -> None:
        """A write transfer: usually a register pointer followed by data bytes."""

    def read(self, length: int) -> bytes:
        """A read transfer of ``length`` bytes from the current register pointer."""


D = TypeVar("D", bound="FakeDevice")


def nack(address: int) -> OSError:
    """The error Linux reports when no device acknowledges ``address``."""
    return OSError(errno.EREMOTEIO, f"{os.strerror(errno.EREMOTEIO)} (address 0x{address:02X})")


class FakeI2CBus:
    """One emulated bus: devices by address, and multiplexers that route to devices behind them.

    ``transfers`` records every transfer as ``(address, "w" | "r", bytes)`` for assertions.
    """

    def __init__(self, number: int) -> None:
        self.number = number
        self.devices: dict[int, FakeDevice] = {}
        self.transfers: list[tuple[int, str, bytes]] = []
        # Transactions come from one worker thread per bus in the drivers; the lock keeps the
        # emulation consistent even if a test drives one bus from several threads.
        self.lock = threading.RLock()

    def attach(self, address: int, device: D) -> D:
        """Put ``device`` on the bus at ``address``; returns it."""
        if address in self.devices:
            raise ValueError(f"bus {self.number}: address 0x{address:02X} is taken")
        self.devices[address] = device
        return device

    def resolve(self, address: int) -> FakeDevice:
        """The device that answers ``address`` now; raises ``OSError`` like a NACK or a clash."""
        device = self.devices.get(address)
        if device is not None:
            return device
        behind = [
            mux.channels[channel][address]
            for mux in self.devices.values()
            if isinstance(mux, FakeTCA9548A)
            for channel in mux.enabled_channels()
            if address in mux.channels.get(channel, {})
        ]
        if not behind:
            raise nack(address)
        if len(behind) > 1:
            # Two devices answering one address at once corrupt each other's data.
            raise OSError(errno.EIO, f"bus conflict: {len(behind)} devices at 0x{address:02X}")
        return behind[0]

    def write(self, address: int, data: bytes) -> None:
        """One write transfer to ``address``."""
        with self.lock:
            self.transfers.append((address, "w", bytes(data)))
            self.resolve(address).write(bytes(data))

    def read(self, address: int, length: int) -> bytes:
        """One read transfer from ``address``."""
        with self.lock:
            data = bytes(self.resolve(address).read(length))
            self.transfers.append((address, "r", data))
            return data


def _check(name: str, value: int, bits: int) -> int:
    if not 0 <= value < 1 << bits:
        raise ValueError(f"{name} {value} does not fit in {bits} bits")
    return value


class FakeSMBus:
    """The ``smbus2.SMBus`` methods the drivers use, on an emulated bus.

    Out-of-range arguments raise ``ValueError`` (real ``smbus2`` would silently truncate them,
    which would hide a driver bug). Using a closed handle raises ``OSError`` (EBADF).
    """

    def __init__(self, bus: FakeI2CBus) -> None:
        self.bus = bus
        self.closed = False

    def _open_bus(self) -> FakeI2CBus:
        if self.closed:
            raise OSError(errno.EBADF, "the SMBus handle is closed")
        return self.bus

    def write_quick(self, i2c_addr: int, force: bool | None = None) -> None:
        """Address the device without data (a probe)."""
        self._open_bus().write(i2c_addr, b"")

    def read_byte(self, i2c_addr: int, force: bool | None = None) -> int:
        """Read one byte without setting a register."""
        return self._open_bus().read(i2c_addr, 1)[0]

    def write_byte(self, i2c_addr: int, value: int, force: bool | None = None) -> None:
        """Write one byte without a register (a TCA9548A's channel mask)."""
        self._open_bus().write(i2c_addr, bytes([_check("value", value, 8)]))

    def read_byte_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int:
        """Read the byte at ``register``."""
        bus = self._open_bus()
        with bus.lock:
            bus.write(i2c_addr, bytes([_check("register", register, 8)]))
            return bus.read(i2c_addr, 1)[0]

    def write_byte_data(
        self, i2c_addr: int, register: int, value: int, force: bool | None = None
    ) -> None:
        """Write ``value`` to ``register``."""
        data = bytes([_check("register", register, 8), _check("value", value, 8)])
        self._open_bus().write(i2c_addr, data)

    def read_word_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int:
        """Read two bytes from ``register``; the first byte on the wire is the low byte."""
        bus = self._open_bus()
        with bus.lock:
            bus.write(i2c_addr, bytes([_check("register", register, 8)]))
            low, high = bus.read(i2c_addr, 2)
        return low | high << 8

    def write_word_data(
        self, i2c_addr: int, register: int, value: int, force: bool | None = None
    ) -> None:
        """Write two bytes to ``register``, the low byte first on the wire."""
        _check("value", value, 16)
        data = bytes([_check("register", register, 8), value & 0xFF, value >> 8])
        self._open_bus().write(i2c_addr, data)

    def read_i2c_block_data(
        self, i2c_addr: int, register: int, length: int, force: bool | None = None
    ) -> list[int]:
        """Read ``length`` bytes starting at ``register``."""
        bus = self._open_bus()
        with bus.lock:
            bus.write(i2c_addr, bytes([_check("register", register, 8)]))
            return list(bus.read(i2c_addr, length))

    def write_i2c_block_data(
        self, i2c_addr: int, register: int, data: list[int], force: bool | None = None
    ) -> None:
        """Write ``data`` starting at ``register``."""
        payload = bytes([_check("register", register, 8), *(_check("byte", b, 8) for b in data)])
        self._open_bus().write(i2c_addr, payload)

    def close(self) -> None:
        """Close the handle (idempotent)."""
        self.closed = True

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class FakeI2C:
    """Numbered emulated buses; :meth:`smbus` is an ``smbus_factory`` for the drivers."""

    def __init__(self) -> None:
        self.buses: dict[int, FakeI2CBus] = {}
        self.handles: list[FakeSMBus] = []

    def bus(self, number: int) -> FakeI2CBus:
        """The bus with this number, created on first use (to attach devices)."""
        if number not in self.buses:
            self.buses[number] = FakeI2CBus(number)
        return self.buses[number]

    def smbus(self, number: int) -> FakeSMBus:
        """Open bus ``number``, like ``smbus2.SMBus(number)``; unknown buses do not exist."""
        if number not in self.buses:
            raise FileNotFoundError(errno.ENOENT, "No such file or directory", f"/dev/i2c-{number}")
        handle = FakeSMBus(self.buses[number])
        self.handles.append(handle)
        return handle


class FakeTSL45315:
    """A TSL45315 light sensor (docs/sensors.md): command bit, power state, integration time.

    ``lux`` is a number or a callable read at every conversion. The 16-bit count is
    ``lux / multiplier`` (multiplier 1/2/4 for 400/200/100 ms) while powered on; when powered down
    the last count stays. ``ident`` is the ID register (0xA0 for a TSL45315).
    """

    CONTROL, CONFIG, DATALOW, DATAHIGH, ID = 0x00, 0x01, 0x04, 0x05, 0x0A
    MULTIPLIER: ClassVar[dict[int, int]] = {
        0: 1,
        1: 2,
        2: 4,
        3: 4,
    }  # CONFIG TCNTRL; 3 is reserved, treat as 100 ms

    def __init__(self, lux: float | Callable[[], float] = 0.0, ident: int = 0xA0) -> None:
        self.lux = lux
        self.registers = bytearray(0x10)
        self.registers[self.ID] = ident
        self.pointer = 0

    @property
    def powered(self) -> bool:
        """Whether CONTROL selects normal (continuous) operation."""
        return self.registers[self.CONTROL] & 0x03 == 0x03

    @property
    def integration_ms(self) -> int:
        """The integration time CONFIG selects."""
        return {0: 400, 1: 200}.get(self.registers[self.CONFIG] & 0x03, 100)

    def _count(self) -> int:
        lux = self.lux() if callable(self.lux) else self.lux
        multiplier = self.MULTIPLIER[self.registers[self.CONFIG] & 0x03]
        return max(0, min(0xFFFF, int(lux / multiplier)))

    def write(self, data: bytes) -> None:
        """Command byte (register pointer), then data for CONTROL/CONFIG (auto-increment)."""
        if not data:
            return
        if not data[0] & 0x80:
            # Without the command bit the chip ignores the transfer; a NACK makes that visible.
            raise OSError(errno.EREMOTEIO, "TSL45315: register access without the command bit")
        self.pointer = data[0] & 0x1F
        for value in data[1:]:
            if self.pointer == self.CONTROL:
                self.registers[self.CONTROL] = value & 0x03
            elif self.pointer == self.CONFIG:
                self.registers[self.CONFIG] = value & 0x0B
            self.pointer = (self.pointer + 1) & 0x1F

    def read(self, length: int) -> bytes:
        """Registers from the pointer on; reading DATALOW converts the current lux."""
        if self.pointer == self.DATALOW and self.powered:
            # Reading DATALOW latches DATAHIGH, so a word read is one consistent sample.
            count = self._count()
            self.registers[self.DATALOW] = count & 0xFF
            self.registers[self.DATAHIGH] = count >> 8
        out = bytearray()
        for _ in range(length):
            out.append(self.registers[self.pointer] if self.pointer < len(self.registers) else 0)
            self.pointer = (self.pointer + 1) & 0x1F
        return bytes(out)


class FakeTCA9548A:
    """A TCA9548A 8-channel multiplexer: one control byte, bit c enables channel c.

    Attach devices behind a channel with :meth:`attach`; they answer only while it is enabled.
    ``selections`` records every control byte written.
    """

    def __init__(self) -> None:
        self.control = 0
        self.channels: dict[int, dict[int, FakeDevice]] = {}
        self.selections: list[int] = []

    def attach(self, channel: int, address: int, device: D) -> D:
        """Put ``device`` at ``address`` behind ``channel``; returns it."""
        if not 0 <= channel <= 7:
            raise ValueError(f"channel {channel} is not 0..7")
        self.channels.setdefault(channel, {})[address] = device
        return device

    def enabled_channels(self) -> list[int]:
        """The channels the control byte enables."""
        return [c for c in range(8) if self.control >> c & 1]

    def write(self, data: bytes) -> None:
        """Each byte becomes the control register (the channel mask)."""
        for value in data:
            self.control = value
            self.selections.append(value)

    def read(self, length: int) -> bytes:
        """The control register."""
        return bytes([self.control] * length)


class FakeADS1115:
    """An ADS1115 16-bit ADC: pointer register, config, single-shot and continuous conversions.

    Registers travel high byte first. ``voltage`` is a number or a callable taking the input
    name (``"AIN0-AIN1"``, ..., ``"AIN3"``) and returning volts, sampled when a conversion starts.
    A single-shot conversion stays busy (OS bit 0) for ``busy_reads`` reads of the config register
    (0: done at once). ``conversions`` counts started conversions.
    """

    CONVERSION, CONFIG, LO_THRESH, HI_THRESH = 0, 1, 2, 3
    RANGES = (6.144, 4.096, 2.048, 1.024, 0.512, 0.256, 0.256, 0.256)
    DEFAULT_CONFIG = 0x8583

    def __init__(
        self, voltage: float | Callable[[str], float] = 0.0, *, busy_reads: int = 0
    ) -> None:
        self.voltage = voltage
        self.busy_reads = busy_reads
        self.registers = [0x0000, self.DEFAULT_CONFIG, 0x8000, 0x7FFF]
        self.pointer = self.CONVERSION
        self.conversions = 0
        self._busy = 0
        self._pending = 0

    @property
    def inputs(self) -> str:
        """The input pair the config register selects."""
        return ADS1115_INPUTS[self.registers[self.CONFIG] >> 12 & 0x7]

    @property
    def range_volts(self) -> float:
        """The full-scale range the PGA bits select."""
        return self.RANGES[self.registers[self.CONFIG] >> 9 & 0x7]

    @property
    def single_shot(self) -> bool:
        """Whether the MODE bit selects single-shot (power-down) mode."""
        return bool(self.registers[self.CONFIG] & 0x0100)

    def _sample(self) -> int:
        volts = self.voltage(self.inputs) if callable(self.voltage) else self.voltage
        counts = round(volts / self.range_volts * 32768)
        return max(-32768, min(32767, counts)) & 0xFFFF

    def write(self, data: bytes) -> None:
        """Pointer byte, then optionally a register value high byte first."""
        if not data:
            return
        self.pointer = data[0] & 0x03
        if len(data) < 3:
            return  # a pointer write before a read
        value = data[1] << 8 | data[2]
        if self.pointer == self.CONFIG:
            # Bit 15 is a command (start) on write and a status on read; it is not stored.
            self.registers[self.CONFIG] = value & 0x7FFF | 0x8000
            if value & 0x8000 and self.single_shot and not self._busy:
                self.conversions += 1
                self._pending = self._sample()
                self._busy = self.busy_reads
                if not self._busy:
                    self.registers[self.CONVERSION] = self._pending
        elif self.pointer != self.CONVERSION:  # the conversion register is read-only
            self.registers[self.pointer] = value

    def read(self, length: int) -> bytes:
        """The pointed register, high byte first; the config's OS bit shows busy or idle."""
        if self.pointer == self.CONFIG:
            value = self.registers[self.CONFIG]
            if self._busy:
                value &= 0x7FFF
                self._busy -= 1
                if not self._busy:
                    self.registers[self.CONVERSION] = self._pending
        else:
            if self.pointer == self.CONVERSION and not self.single_shot:
                self.conversions += 1
                self.registers[self.CONVERSION] = self._sample()
            value = self.registers[self.pointer]
        data = bytes([value >> 8, value & 0xFF])
        return (data * (length // 2 + 1))[:length]
