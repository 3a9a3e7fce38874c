"""Fixtures shared by every test directory (keep this file small and generic)."""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest

from needs import require_binary


@pytest.fixture
async def dbus_address() -> AsyncIterator[str]:
    """The address of a private ``dbus-daemon`` that runs for the duration of one test."""
    require_binary("dbus-daemon")
    from sim_stub.fake_medulla import private_bus

    async with private_bus() as address:
        yield address
