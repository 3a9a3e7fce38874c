"""Fixtures shared by every test directory (keep this file small and generic)."""

from __future__ import annotations

import os
import shutil
from collections.abc import AsyncIterator

import pytest


def require_binary(name: str) -> None:
    """Skip the test when the program ``name`` is missing, except in CI (``CI=true``), where
    ``.ci/run`` installs it: a skipped test there would hide a missing install step."""
    if shutil.which(name) is None:
        if os.environ.get("CI", "").lower() in ("true", "1"):
            pytest.fail(f"{name} is not installed, but CI must run the tests that need it")
        pytest.skip(f"{name} is not installed")


@pytest.fixture
async def dbus_address() -> AsyncIterator[str]:
    """The address of a private ``dbus-daemon`` that runs for the duration of one test."""
    require_binary("dbus-daemon")
    from sim_stub.fake_medulla import private_bus

    async with private_bus() as address:
        yield address
