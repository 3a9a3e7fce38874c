"""The ``body_factory`` fixture: one parameter per entry of ``bodies.FACTORIES``."""

from __future__ import annotations

from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import AsyncExitStack

import pytest

from .bodies import FACTORIES, BodyUnderTest


@pytest.fixture(params=FACTORIES, ids=lambda factory: factory.__name__)
async def body_factory(
    request: pytest.FixtureRequest,
) -> AsyncIterator[Callable[[], Awaitable[BodyUnderTest]]]:
    """Build bodies of one kind; whatever they needed is torn down after the test."""
    async with AsyncExitStack() as stack:

        async def make() -> BodyUnderTest:
            return await request.param(stack)

        yield make
