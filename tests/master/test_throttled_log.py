"""The throttled log: a bounded number of lines per window, and a count of the rest."""

from __future__ import annotations

import logging

import pytest

from master_service.throttled_log import ThrottledLog


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def log(caplog):
    caplog.set_level(logging.INFO, logger="throttled")
    clock = Clock()
    throttled = ThrottledLog(
        logging.getLogger("throttled"), "refused connections", lines=3, window=60.0, clock=clock
    )
    return throttled, clock, caplog


def messages(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records]


def test_at_most_the_limit_per_window_and_a_count_of_the_rest(log):
    throttled, clock, caplog = log
    written = [throttled.log(logging.WARNING, "refused %d", i) for i in range(1000)]
    assert written == [True] * 3 + [False] * 997
    assert messages(caplog) == ["refused 0", "refused 1", "refused 2"]
    clock.t += 60.0  # the next window: first the count, then room again
    assert throttled.log(logging.WARNING, "refused %d", 1000)
    assert messages(caplog)[3:] == [
        "997 more refused connections were not logged (at most 3 lines per 60 s)",
        "refused 1000",
    ]
    assert throttled.suppressed == 0 and throttled.suppressed_total == 997


def test_a_quiet_window_writes_no_count(log):
    throttled, clock, caplog = log
    throttled.log(logging.INFO, "one")
    clock.t += 59.0
    throttled.log(logging.INFO, "two")
    clock.t += 120.0
    throttled.log(logging.INFO, "three")
    throttled.flush()
    assert messages(caplog) == ["one", "two", "three"]


def test_flush_reports_what_was_held_back(log):
    throttled, _, caplog = log
    for i in range(5):
        throttled.log(logging.INFO, "refused %d", i)
    throttled.flush()
    throttled.flush()  # nothing more to report
    assert messages(caplog)[-1].startswith("2 more refused connections were not logged")
    assert len(caplog.records) == 4 and caplog.records[-1].levelno == logging.WARNING


def test_nonsense_limits_are_refused():
    with pytest.raises(ValueError):
        ThrottledLog(logging.getLogger("x"), "x", lines=0)
