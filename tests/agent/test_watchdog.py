"""The watchdog, on fake time: stalls stop the motors in time, feeds and disarming do not, and a
failing or hanging stop never ends the watching."""

from __future__ import annotations

import asyncio
import logging
import time

import pytest

from robot_agent.watchdog import (
    CHECK_PERIOD,
    MAX_STOP_DELAY,
    REASON_STALL,
    RETRY_MAX,
    STOP_TIMEOUT,
    TIMEOUT,
    Watchdog,
)


class FakeTime:
    """A time source and a sleep that only move when the test calls :meth:`advance`."""

    def __init__(self) -> None:
        self.now = 0.0
        self._sleepers: list[tuple[float, asyncio.Future[None]]] = []

    def time(self) -> float:
        return self.now

    async def sleep(self, delay: float) -> None:
        future = asyncio.get_running_loop().create_future()
        self._sleepers.append((self.now + delay, future))
        await future

    async def advance(self, seconds: float) -> None:
        """Move time forward, waking each sleeper at its deadline and letting the tasks run."""
        end = self.now + seconds
        await _settle()
        while True:
            self._sleepers = [(t, f) for t, f in self._sleepers if not f.done()]
            due = [t for t, _ in self._sleepers if t <= end]
            if not due:
                break
            self.now = max(self.now, min(due))
            for t, future in self._sleepers:
                if t <= self.now:
                    future.set_result(None)
            await _settle()
        self.now = end
        await _settle()


async def _settle() -> None:
    # Enough loop iterations for a woken check to run a whole stop attempt.
    for _ in range(30):
        await asyncio.sleep(0)


class Motors:
    """A fake ``body.stop`` that records the (fake) time of each call; it can fail or hang."""

    def __init__(self, clock: FakeTime) -> None:
        self.clock = clock
        self.calls: list[float] = []
        self.mode = "ok"  # "ok", "fail" or "hang"

    async def stop(self) -> None:
        self.calls.append(self.clock.now)
        if self.mode == "fail":
            raise OSError("D-Bus is gone")
        if self.mode == "hang":
            await asyncio.Event().wait()


@pytest.fixture
def clock() -> FakeTime:
    return FakeTime()


@pytest.fixture
def motors(clock) -> Motors:
    return Motors(clock)


def watchdog(clock: FakeTime, motors: Motors, **kwargs) -> Watchdog:
    return Watchdog(motors.stop, now=clock.time, sleep=clock.sleep, **kwargs)


def test_the_defaults_meet_the_300_ms_limit():
    assert TIMEOUT + CHECK_PERIOD <= MAX_STOP_DELAY == 0.3
    # A 10 Hz loop feeds every 0.1 s: one late step must not trip it.
    assert TIMEOUT > 2 * 0.1


@pytest.mark.parametrize(
    "kwargs",
    [{"timeout": 0.3}, {"timeout": 0.2, "period": 0.11}, {"period": 0}, {"stop_timeout": -1}],
    ids=["timeout-too-long", "period-too-long", "zero-period", "negative-stop-timeout"],
)
def test_settings_that_break_the_limit_are_refused(kwargs):
    with pytest.raises(ValueError):
        Watchdog(lambda: asyncio.sleep(0), **kwargs)


async def test_a_stall_stops_the_motors_within_300_ms(clock, motors, caplog):
    async with watchdog(clock, motors) as wd:
        wd.arm()
        await clock.advance(0.24)
        assert motors.calls == [] and not wd.tripped
        await clock.advance(0.06)
        assert len(motors.calls) == 1
        assert TIMEOUT < motors.calls[0] <= MAX_STOP_DELAY
        assert wd.tripped_reason == REASON_STALL and wd.stopped and not wd.armed
        assert "stalled" in caplog.text
        # One stop per trip: the watchdog does not keep stopping a stopped robot.
        await clock.advance(2.0)
        assert len(motors.calls) == 1


async def test_a_stall_long_after_the_last_feed_is_timed_from_that_feed(clock, motors):
    async with watchdog(clock, motors) as wd:
        wd.arm()
        for _ in range(30):  # 3 s of a healthy 10 Hz loop
            await clock.advance(0.1)
            wd.feed()
        last_feed = clock.now
        await clock.advance(0.5)
        assert len(motors.calls) == 1
        assert TIMEOUT < motors.calls[0] - last_feed <= MAX_STOP_DELAY


async def test_a_fed_watchdog_does_not_stop(clock, motors):
    async with watchdog(clock, motors) as wd:
        wd.arm()
        for _ in range(50):  # every step 0.2 s late is still inside the timeout
            await clock.advance(0.2)
            wd.feed()
        assert motors.calls == [] and not wd.tripped


@pytest.mark.parametrize("armed", [False, None], ids=["disarmed", "never-armed"])
async def test_a_disarmed_watchdog_does_not_stop(clock, motors, armed):
    async with watchdog(clock, motors) as wd:
        if armed is False:
            wd.arm()
            wd.disarm()
        await clock.advance(5.0)
        assert motors.calls == [] and not wd.tripped and not wd.armed


async def test_arming_counts_from_the_arming_not_from_an_old_feed(clock, motors):
    async with watchdog(clock, motors) as wd:
        await clock.advance(10.0)  # idle between evaluations, never fed
        wd.arm()
        await clock.advance(0.2)
        assert motors.calls == []


async def test_trip_stops_at_once_and_keeps_the_first_reason(clock, motors, caplog):
    async with watchdog(clock, motors, armed=True) as wd:
        await clock.advance(0.1)
        assert await wd.trip("link lost") is True
        assert motors.calls == [0.1]  # no time passed
        assert wd.tripped_reason == "link lost" and wd.stopped and not wd.armed
        assert await wd.trip("read failures") is True
        assert wd.tripped_reason == "link lost" and len(motors.calls) == 1
        assert "link lost" in caplog.text


async def test_trip_works_when_disarmed_and_outside_the_context(clock, motors):
    wd = watchdog(clock, motors)
    assert await wd.trip("shutdown") is True
    assert motors.calls == [0.0]


async def test_a_tripped_watchdog_ignores_feeds_until_armed_again(clock, motors):
    async with watchdog(clock, motors) as wd:
        wd.arm()
        await wd.trip("link lost")
        wd.feed()
        assert wd.tripped
        wd.arm()
        assert not wd.tripped and wd.tripped_reason is None and not wd.stopped
        await clock.advance(0.2)
        assert len(motors.calls) == 1
        await clock.advance(0.2)  # armed afresh, so a new stall trips again
        assert len(motors.calls) == 2 and wd.tripped_reason == REASON_STALL


async def test_a_stop_that_keeps_failing_is_retried_at_a_bounded_rate(clock, motors):
    # A robot that went away: every stop fails at once. Retrying on every check (40 a second)
    # would flood medulla with some 160 messages a second for as long as the robot is gone.
    motors.mode = "fail"
    async with watchdog(clock, motors) as wd:
        wd.arm()
        await clock.advance(0.3)
        first = len(motors.calls)
        await clock.advance(10.0)
        retries = len(motors.calls) - first
    assert 8 <= retries <= 10 / RETRY_MAX + 6  # at most one a second once the pauses have grown


@pytest.mark.parametrize("mode", ["hang", "fail"])
async def test_a_failing_or_hanging_stop_is_logged_and_retried(clock, motors, caplog, mode):
    caplog.set_level(logging.INFO, logger="robot_agent.watchdog")
    motors.mode = mode
    async with watchdog(clock, motors) as wd:
        wd.arm()
        await clock.advance(0.28)  # the stall is seen at 0.275 s at the latest
        assert len(motors.calls) == 1 and wd.tripped and not wd.stopped
        await clock.advance(STOP_TIMEOUT + 0.01)
        errors = [r for r in caplog.records if r.levelno == logging.ERROR]
        assert any("stopping the motors failed" in r.getMessage() for r in errors)
        expected = "no answer" if mode == "hang" else "D-Bus is gone"
        assert expected in caplog.text
        # Still watching: it retries, and quietly (one error line, not one per attempt).
        await clock.advance(2.0)
        assert len(motors.calls) > 2
        assert len([r for r in caplog.records if r.levelno >= logging.WARNING]) == 2  # stall, fail
        motors.mode = "ok"
        await clock.advance(RETRY_MAX + STOP_TIMEOUT + 0.1)
        assert wd.stopped and wd.tripped_reason == REASON_STALL
        assert "motors stopped after" in caplog.text
        calls = len(motors.calls)
        await clock.advance(1.0)
        assert len(motors.calls) == calls


async def test_trip_with_a_hanging_stop_returns_after_the_stop_timeout(clock, motors):
    motors.mode = "hang"
    wd = watchdog(clock, motors)
    trip = asyncio.create_task(wd.trip("link lost"))
    await clock.advance(STOP_TIMEOUT - 0.01)
    assert not trip.done()
    await clock.advance(0.02)
    assert trip.done() and trip.result() is False
    assert wd.tripped_reason == "link lost" and not wd.stopped


async def test_a_stop_that_is_not_a_coroutine_is_survived(clock, caplog):
    def broken() -> None:
        raise RuntimeError("not async")

    async with Watchdog(broken, now=clock.time, sleep=clock.sleep, armed=True) as wd:
        await clock.advance(0.3)
        assert wd.tripped and not wd.stopped
        assert "not async" in caplog.text


async def test_the_context_starts_once_and_ends_cleanly(clock, motors):
    wd = watchdog(clock, motors)
    async with wd:
        with pytest.raises(RuntimeError):
            await wd.__aenter__()
    # After the exit nothing watches any more.
    wd.arm()
    await clock.advance(1.0)
    assert motors.calls == []


async def test_real_time_smoke():
    """With the real clock and sleep, an unfed armed watchdog stops the motors in about 0.275 s.

    The bound here is loose on purpose (a loaded CI machine); the exact arithmetic is checked on
    fake time above.
    """
    stopped = asyncio.Event()
    start = time.monotonic()

    async def stop() -> None:
        stopped.set()

    async with Watchdog(stop, armed=True):
        await asyncio.wait_for(stopped.wait(), timeout=2.0)
    elapsed = time.monotonic() - start
    assert TIMEOUT < elapsed < 1.0


async def test_a_stop_begun_before_arming_does_not_cover_the_next_trip(clock):
    """A slow stop attempt that succeeds after ``arm()`` must not mark the new arming stopped.

    Otherwise the next stall trips the watchdog but issues no stop ("already stopped").
    """
    calls: list[float] = []
    release = asyncio.Event()

    async def stop() -> None:
        calls.append(clock.now)
        if len(calls) == 1:
            await release.wait()  # slow, but it succeeds

    async with Watchdog(stop, now=clock.time, sleep=clock.sleep) as wd:
        trip = asyncio.create_task(wd.trip("stop failed"))
        await clock.advance(0.1)
        assert len(calls) == 1 and not trip.done()
        wd.arm()  # the next evaluation starts while that attempt is still in flight
        release.set()
        await clock.advance(0.0)
        assert await trip is True
        assert not wd.stopped and not wd.tripped
        await clock.advance(0.3)  # the new evaluation's loop stalls
        assert wd.tripped_reason == REASON_STALL
        assert len(calls) == 2  # a fresh stop for the stall
        assert wd.stopped
