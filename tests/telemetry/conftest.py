"""Fixtures of the telemetry tests: a real ``mosquitto`` broker (a missing one skips the test
outside CI and fails it in CI, which installs it), a closed port, and subscribers. See
``telemetry_helpers``."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from telemetry_helpers import Broker, Subscriber, free_port, mosquitto_binary

from needs import require_binary


@pytest.fixture
def mosquitto(tmp_path: Path) -> Iterator[Broker]:
    """A running broker for one test, stopped afterwards."""
    binary = mosquitto_binary()
    if binary is None:
        require_binary("mosquitto")
    broker = Broker(binary, tmp_path, free_port())
    broker.start()
    try:
        yield broker
    finally:
        broker.stop()


@pytest.fixture
def closed_port() -> int:
    """A loopback port nothing listens on: connections are refused at once."""
    return free_port()


@pytest.fixture
def subscriber() -> Callable[..., Subscriber]:
    """Make a :class:`Subscriber` for a broker's port (``async with subscriber(port): ...``)."""
    return Subscriber
