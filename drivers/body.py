"""The ``Body`` seam: what the control loop needs from a robot, real or simulated."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from types import TracebackType
from typing import TYPE_CHECKING, ClassVar, Self

if TYPE_CHECKING:
    # Only annotations here: importing the drivers (as ``surprise-agent --stop-motors`` does, in
    # systemd's stop timeout on a slow Pi) must not import numpy.
    import numpy as np


@dataclass(frozen=True, slots=True)
class PartReading:
    """One part of a body read on its own (a preflight check): its ``sensors`` and ``values``
    (normalised, in that order), or the ``error`` that kept it from answering."""

    part: str
    sensors: tuple[str, ...]
    values: tuple[float, ...] = ()
    error: str | None = None


@dataclass(frozen=True, slots=True)
class SensorFrame:
    """One reading of every sensor of a body.

    ``values`` are normalised to [0, 1] in the order of :attr:`Body.sensors`; ``timestamp`` is the
    time of the reading on the body's clock, in seconds.
    """

    values: np.ndarray
    timestamp: float


class Body(ABC):
    """A robot: read its sensors, drive its wheels, stop.

    Use it as an async context manager; leaving the context always stops the motors, whatever the
    exit path. ``drive`` takes normalised wheel speeds in [-1, 1] (values outside are clamped; the
    body maps 1 to its calibrated maximum speed).
    """

    #: False for a body whose ``read``, ``drive`` and ``stop`` never wait for I/O (a simulated
    #: body computes its answer at once): the control loop then needs no timeout around them.
    blocking: ClassVar[bool] = True

    @property
    @abstractmethod
    def sensors(self) -> tuple[str, ...]:
        """Names of the values :meth:`read` returns, in that order (see
        ``minimize_surprise.sensors``)."""

    async def open(self) -> None:  # noqa: B027 - optional hook, most bodies need no set-up
        """Acquire the hardware (connect, power on, calibrate). Called by ``__aenter__``."""

    async def close(self) -> None:
        """Stop the motors and release the hardware. Called by ``__aexit__``; idempotent."""
        await self.stop()

    async def recover(self) -> None:  # noqa: B027 - optional hook, a simulated body never fails
        """Get the hardware back after ``minimize_surprise.errors.RobotUnreachableError``
        (reconnect, reattach, reload); raises ``HardwareError`` while that is not possible yet.
        Called again and again, with pauses, until it returns; also for a body whose ``open()``
        failed."""

    @abstractmethod
    async def read(self) -> SensorFrame:
        """Read every sensor once. Raises ``minimize_surprise.errors.HardwareError`` on failure."""

    async def read_parts(self) -> list[PartReading]:
        """Each part read on its own, so that one broken part does not hide the others (a
        preflight check); never raises. A body of one part reads itself whole."""
        try:
            frame = await self.read()
        except Exception as exc:
            return [PartReading("body", self.sensors, error=describe_error(exc))]
        values = tuple(float(v) for v in frame.values)
        return [PartReading("body", self.sensors, values)]

    async def read_battery(self) -> float | None:
        """The battery's voltage, or None where this body cannot tell (never a guess). Raises
        ``HardwareError`` when the robot does not answer. Read between evaluations, not per step.
        """
        return None

    async def read_firmware(self) -> int | None:
        """The robot's firmware version (a Thymio's ``_fwversion[0]``), or None where this body
        has none to tell (a simulated robot). Raises ``HardwareError`` when the robot does not
        answer. Read when the agent introduces itself, not per step."""
        return None

    @abstractmethod
    async def drive(self, left: float, right: float) -> None:
        """Set the wheel speeds, normalised to [-1, 1]."""

    @abstractmethod
    async def stop(self) -> None:
        """Set both wheel speeds to zero."""

    async def set_top_led(self, red: float, green: float, blue: float) -> None:
        """Light the top LED in this colour, each channel normalised to [0, 1] (clamped; all 0
        is off). A signal for a camera, never a safety part: callers bound it and go on when it
        fails. Raises ``NotImplementedError`` for a body without one, ``HardwareError`` when
        the robot refuses or does not answer."""
        raise NotImplementedError(f"{type(self).__name__} has no top LED")

    async def __aenter__(self) -> Self:
        await self.open()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()


def describe_error(exc: BaseException) -> str:
    """An exception in one line for a person: its message, or its type when it has none."""
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def led_level(value: float) -> float:
    """An LED channel clamped to [0, 1]; NaN is off."""
    if value != value:  # NaN
        return 0.0
    return 0.0 if value < 0.0 else 1.0 if value > 1.0 else float(value)


def clamp_unit(value: float) -> float:
    """Clamp ``value`` to [-1, 1]; NaN becomes 0 so that a broken network never drives a wheel."""
    if value != value:  # NaN
        return 0.0
    return -1.0 if value < -1.0 else 1.0 if value > 1.0 else float(value)
