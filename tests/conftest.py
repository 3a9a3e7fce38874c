"""Fixtures shared by every test directory (keep this file small and generic)."""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest

from needs import require_binary


@pytest.fixture
async def dbus_address() -> AsyncIterator[str]:
    """The address of a private ``dbus-daemon`` that runs for the duration of one test."""
    require_binary("dbus-daemon")
    from standins.fake_medulla import private_bus

    async with private_bus() as address:
        yield address


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels() -> None:
    """Compile the numba kernels once, before any test runs: a fresh clone compiles them on first
    use (seconds each), which would otherwise land inside some test's real-time timeout."""
    from simulator.warmup import warm_up

    warm_up()
