"""What a real body is composed of: parts that each report some of the sensors."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    import numpy as np  # annotations only: see drivers.body


class Part(Protocol):
    """A piece of hardware reporting ``sensors`` (canonical names, in its own order).

    ``read()`` returns one normalised value per name, in [0, 1]; ``close()`` never raises.
    """

    sensors: tuple[str, ...]

    async def open(self) -> None:
        """Acquire and initialise the hardware; raises ``HardwareError``."""

    async def read(self) -> np.ndarray:
        """One value per sensor name, normalised to [0, 1]; raises ``HardwareError``."""

    async def close(self) -> None:
        """Release the hardware; idempotent, never raises."""


async def gather_all(*awaitables: Awaitable[Any]) -> list[Any]:
    """Await all concurrently; if any failed, raise the first failure once all have finished.

    Unlike a bare ``asyncio.gather`` this never leaves a sibling running (or its exception
    unretrieved) after one fails: each awaitable is bounded by its own timeout, so waiting for all
    is bounded too.
    """
    results = await asyncio.gather(*awaitables, return_exceptions=True)
    for result in results:
        if isinstance(result, BaseException):
            raise result
    return results
