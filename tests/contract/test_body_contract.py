"""What every ``Body`` promises the control loop, whatever is behind it."""

from __future__ import annotations

import math
from collections.abc import Awaitable, Callable

import numpy as np
import pytest

from minimize_surprise.sensors import ALL_SENSORS, check_sensor_names

from .bodies import BodyUnderTest

MakeBody = Callable[[], Awaitable[BodyUnderTest]]
#: Observed speeds may be quantised by the backend (motor units: 1/315 on the Thymio).
SPEED_TOLERANCE = 0.01


async def test_sensor_names_are_known_and_in_canonical_order(body_factory: MakeBody):
    body = (await body_factory()).body
    names = body.sensors
    assert isinstance(names, tuple) and names
    check_sensor_names(names)
    assert list(names) == sorted(names, key=ALL_SENSORS.index)


async def test_read_returns_normalised_finite_values_in_time_order(body_factory: MakeBody):
    body = (await body_factory()).body
    async with body:
        frames = [await body.read() for _ in range(6)]
    for frame in frames:
        assert frame.values.shape == (len(body.sensors),)
        assert np.issubdtype(frame.values.dtype, np.floating)
        assert np.isfinite(frame.values).all()
        assert ((frame.values >= 0.0) & (frame.values <= 1.0)).all(), frame.values
        assert math.isfinite(frame.timestamp)
    stamps = [frame.timestamp for frame in frames]
    assert stamps == sorted(stamps)


async def test_drive_applies_speeds_in_range(body_factory: MakeBody):
    subject = await body_factory()
    async with subject.body as body:
        await body.drive(0.5, -0.25)
        assert await subject.observe_motors() == pytest.approx((0.5, -0.25), abs=SPEED_TOLERANCE)


@pytest.mark.parametrize(
    ("left", "right", "expected"),
    [
        (5.0, -5.0, (1.0, -1.0)),
        (-math.inf, math.inf, (-1.0, 1.0)),
        (math.nan, 0.5, (0.0, 0.5)),
        (1.0000001, math.nan, (1.0, 0.0)),
    ],
)
async def test_drive_clamps_out_of_range_and_nan(
    body_factory: MakeBody, left: float, right: float, expected: tuple[float, float]
):
    subject = await body_factory()
    async with subject.body as body:
        await body.drive(left, right)  # never raises for odd values
        assert await subject.observe_motors() == pytest.approx(expected, abs=SPEED_TOLERANCE)


async def test_stop_sets_both_wheels_to_zero(body_factory: MakeBody):
    subject = await body_factory()
    async with subject.body as body:
        await body.drive(0.7, 0.9)
        await body.stop()
        assert await subject.observe_motors() == (0.0, 0.0)


async def test_leaving_the_context_stops_the_motors(body_factory: MakeBody):
    subject = await body_factory()
    async with subject.body as body:
        await body.drive(0.8, 0.8)
        assert await subject.observe_motors() != (0.0, 0.0)
    assert await subject.observe_motors() == (0.0, 0.0)


async def test_leaving_the_context_by_an_exception_stops_the_motors(body_factory: MakeBody):
    subject = await body_factory()
    with pytest.raises(RuntimeError, match="network diverged"):
        async with subject.body as body:
            await body.drive(-0.6, 0.6)
            raise RuntimeError("network diverged")
    assert await subject.observe_motors() == (0.0, 0.0)


async def test_close_is_idempotent(body_factory: MakeBody):
    body = (await body_factory()).body
    await body.close()  # never opened
    async with body:
        await body.read()
    await body.close()
    await body.close()
