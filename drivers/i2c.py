"""I2C access shared by the sensor drivers: one worker thread per bus, multiplexer channels.

``smbus2`` calls block, so every transaction runs on its bus's single worker thread, never on the
event loop. One thread per bus also serialises the bus: a transaction (select the multiplexer
channel, then the register accesses) runs start to end before the next one begins, so two sensors
behind one multiplexer never interleave; the worker thread is the per-bus lock. Every failure of a
transaction becomes a :class:`~minimize_surprise.errors.HardwareError` in :meth:`I2CBus.run`, the
one place where that translation happens.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Protocol, TypeVar

from drivers.config import MuxConfig
from minimize_surprise.errors import HardwareError, HardwareTimeoutError

T = TypeVar("T")
log = logging.getLogger(__name__)

#: Seconds one transaction may take, excluding waits a driver adds for conversions. A transaction
#: is a few bytes at 100 kHz (well under 1 ms); 0.2 s leaves room for a loaded Pi while still
#: failing a control step of 100 ms promptly. (A transfer that hangs in the kernel is abandoned
#: by this timeout; the worker thread stays busy until the adapter's own timeout frees it.)
TRANSACTION_TIMEOUT = 0.2


class SMBusLike(Protocol):
    """The subset of ``smbus2.SMBus`` the drivers use (``standins.fake_i2c`` emulates it)."""

    def read_byte_data(self, i2c_addr: int, register: int) -> int: ...
    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None: ...
    def read_word_data(self, i2c_addr: int, register: int) -> int: ...
    def write_word_data(self, i2c_addr: int, register: int, value: int) -> None: ...
    def write_byte(self, i2c_addr: int, value: int) -> None: ...
    def close(self) -> None: ...


#: Opens bus number ``n`` (``/dev/i2c-n``); the default is ``smbus2.SMBus``.
SMBusFactory = Callable[[int], SMBusLike]


def default_smbus_factory(bus: int) -> SMBusLike:
    """Open ``/dev/i2c-<bus>`` with ``smbus2`` (imported here so ``drivers`` imports without it)."""
    from smbus2 import SMBus

    return SMBus(bus)


def swap16(word: int) -> int:
    """Swap the two bytes of a 16-bit word.

    SMBus words travel low byte first, but chips such as the ADS1115 send the high byte first.
    """
    return ((word & 0xFF) << 8) | ((word >> 8) & 0xFF)


class I2CBus:
    """One I2C bus: the SMBus handle and the single worker thread that owns it.

    The handle is opened on the first :meth:`acquire` and closed when the last user releases it,
    so several parts share one bus.
    """

    def __init__(self, number: int, factory: SMBusFactory) -> None:
        self.number = number
        self._factory = factory
        self._smbus: SMBusLike | None = None
        self._executor: ThreadPoolExecutor | None = None
        self._users = 0
        # Parts open concurrently; this lock makes the first user open the handle exactly once.
        self._lock = asyncio.Lock()

    async def acquire(self) -> None:
        """Open the bus for one more user (opening ``/dev/i2c-n`` blocks: done on the worker)."""
        async with self._lock:
            if self._users == 0:
                self._executor = ThreadPoolExecutor(1, thread_name_prefix=f"i2c-{self.number}")

                def open_bus(_: object) -> None:
                    self._smbus = self._factory(self.number)

                try:
                    await self._submit(
                        f"open /dev/i2c-{self.number}", open_bus, TRANSACTION_TIMEOUT
                    )
                except BaseException:
                    self._shutdown()
                    raise
            self._users += 1

    async def release(self) -> None:
        """Drop one user; the last one closes the handle and stops the worker. Never raises."""
        async with self._lock:
            if self._users == 0:
                return
            self._users -= 1
            if self._users:
                return
            try:
                await self._submit("close", lambda smbus: smbus.close(), TRANSACTION_TIMEOUT)
            except Exception as exc:  # closing is best effort: report, never raise
                log.warning("closing I2C bus %d failed: %s", self.number, exc)
            finally:
                self._smbus = None
                self._shutdown()

    async def run(
        self,
        operation: str,
        transaction: Callable[[SMBusLike], T],
        timeout: float = TRANSACTION_TIMEOUT,
    ) -> T:
        """Run ``transaction(smbus)`` on the bus's worker thread, bounded by ``timeout`` seconds.

        Raises :class:`HardwareTimeoutError` when it does not finish in time and
        :class:`HardwareError` for any ``OSError`` (a NACK is errno 121, Remote I/O error).
        """
        if self._users == 0:
            raise HardwareError(f"I2C bus {self.number}: {operation} on a bus that is not open")
        return await self._submit(operation, transaction, timeout)

    async def _submit(
        self, operation: str, transaction: Callable[[SMBusLike], T], timeout: float
    ) -> T:
        assert self._executor is not None
        what = f"I2C bus {self.number}: {operation}"

        def call() -> T:
            return transaction(self._smbus)  # type: ignore[arg-type]  # None only while opening

        future = asyncio.get_running_loop().run_in_executor(self._executor, call)
        try:
            async with asyncio.timeout(timeout):
                return await future
        except TimeoutError:
            raise HardwareTimeoutError(what, timeout) from None
        except HardwareError:
            raise
        except OSError as exc:
            raise HardwareError(f"{what} failed: {exc}") from exc

    def _shutdown(self) -> None:
        if self._executor is not None:
            # Never wait: a transfer stuck in the kernel must not block the event loop.
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None


class I2CBuses:
    """The buses of one body, created on demand and shared by every part on the same number."""

    def __init__(self, factory: SMBusFactory | None = None) -> None:
        self._factory = factory or default_smbus_factory
        self._buses: dict[int, I2CBus] = {}

    def get(self, number: int) -> I2CBus:
        """The bus with this number (created, not yet opened, on first request)."""
        if number not in self._buses:
            self._buses[number] = I2CBus(number, self._factory)
        return self._buses[number]


class I2CDevice:
    """A device at ``address`` on ``bus``, optionally behind a TCA9548A multiplexer channel."""

    def __init__(self, bus: I2CBus, address: int, mux: MuxConfig | None = None) -> None:
        self.bus = bus
        self.address = address
        self.mux = mux

    def __str__(self) -> str:
        where = f"bus {self.bus.number}, address 0x{self.address:02X}"
        if self.mux is not None:
            where += f" behind multiplexer 0x{self.mux.address:02X} channel {self.mux.channel}"
        return where

    async def open(self) -> None:
        """Open the bus for this device."""
        await self.bus.acquire()

    async def close(self) -> None:
        """Release the bus. Never raises."""
        await self.bus.release()

    async def run(
        self,
        operation: str,
        transaction: Callable[[SMBusLike], T],
        timeout: float = TRANSACTION_TIMEOUT,
    ) -> T:
        """Run ``transaction`` with this device's multiplexer channel selected first.

        The channel is selected again before every transaction, not cached, so a multiplexer that
        lost its state (brown-out, another process) is corrected at once.
        """
        mux = self.mux
        if mux is None:
            return await self.bus.run(f"0x{self.address:02X} {operation}", transaction, timeout)

        def selected(smbus: SMBusLike) -> T:
            smbus.write_byte(mux.address, 1 << mux.channel)
            return transaction(smbus)

        what = f"0x{self.address:02X} (mux 0x{mux.address:02X}/{mux.channel}) {operation}"
        return await self.bus.run(what, selected, timeout)
