"""Fixtures for the driver tests: a fake asebamedulla on a private bus, emulated I2C."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest

from drivers.config import ThymioConfig
from standins.fake_i2c import FakeI2C
from standins.fake_medulla import FakeMedulla, StaticThymioModel, serve_fake_medulla

#: Generous for the fake, which answers in about a millisecond; hang tests use 0.05 s.
TEST_TIMEOUT = 1.0


@pytest.fixture
def model() -> StaticThymioModel:
    """A robot at rest in front of an obstacle on a bright floor."""
    return StaticThymioModel(
        prox=[0, 1125, 2250, 4500, 6000, 0, 900], reflected=[1023, 0], delta=[512, 100]
    )


@pytest.fixture
async def medulla(dbus_address: str, model: StaticThymioModel) -> AsyncIterator[FakeMedulla]:
    """The fake medulla serving ``model`` on the private bus."""
    async with serve_fake_medulla(dbus_address, model) as fake:
        yield fake


@pytest.fixture
def thymio_config(dbus_address: str) -> Callable[..., ThymioConfig]:
    """Build a ``ThymioConfig`` for the private bus; keyword arguments override fields."""

    def make(**overrides: Any) -> ThymioConfig:
        fields: dict[str, Any] = {"bus": dbus_address, "timeout": TEST_TIMEOUT}
        fields.update(overrides)
        return ThymioConfig(**fields)

    return make


@pytest.fixture
def i2c() -> FakeI2C:
    """An empty emulated I2C world (attach devices to ``i2c.bus(n)``)."""
    return FakeI2C()
