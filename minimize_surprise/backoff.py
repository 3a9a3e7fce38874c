"""Capped exponential backoff with jitter, shared by every client that reconnects (the robot's
link to the master, the telemetry publishers, the live view).

Pure: the only randomness comes from an injectable ``random.Random``, so tests repeat exactly.
"""

from __future__ import annotations

import random
from typing import Annotated

import msgspec

from minimize_surprise.config import Probability, Strict

__all__ = ["Backoff", "BackoffConfig"]

_Seconds = Annotated[float, msgspec.Meta(gt=0.0, le=3600.0)]


class BackoffConfig(Strict, frozen=True):
    """Delays between connection attempts: ``initial`` doubling per failed attempt up to ``max``
    (seconds), each shortened by a random fraction of up to ``jitter``, so that a swarm whose
    server comes back does not reconnect in one burst."""

    #: seconds before the first new attempt; the delay doubles after every failed attempt
    initial: _Seconds = 0.5
    #: the longest delay, in seconds
    max: _Seconds = 30.0
    #: each delay is shortened by a random fraction of up to this much of itself
    jitter: Probability = 0.25

    def __post_init__(self) -> None:
        if self.max < self.initial:
            raise ValueError(f"`max`: must be at least initial ({self.initial})")


class Backoff:
    """The delays of :class:`BackoffConfig`: ``min(max, initial * 2**n)`` after ``n`` failures,
    shortened by up to ``jitter`` of itself at random (so never longer than ``max``)."""

    def __init__(self, config: BackoffConfig, rng: random.Random | None = None) -> None:
        self.config = config
        self.rng = rng if rng is not None else random.Random()
        #: failed attempts since the last :meth:`reset`
        self.attempts = 0

    def reset(self) -> None:
        """A connection succeeded: the next delay is the initial one again."""
        self.attempts = 0

    def next_delay(self) -> float:
        """The delay before the next attempt, in seconds."""
        c = self.config
        # Cap the exponent, not the power: a week-long outage must not overflow a float.
        delay = min(c.max, c.initial * 2.0 ** min(self.attempts, 32))
        self.attempts += 1
        return delay * (1.0 - c.jitter * self.rng.random())
