"""Events of an experiment: the arena changes while the swarm evolves (docs/changing-arenas.md).

An experiment's ``events`` list says what changes and when: each event is one of the kinds below
(``kind`` names it) and happens between two evaluations, before counted evaluation
``evaluation`` (so that evaluation is the first in the changed arena) or at the first gap
between evaluations once the run has been served ``seconds`` seconds. What each kind does to a
simulated world is :mod:`simulator.events`; on real robots the run pauses and asks the person to
make the change. This module holds only the typed description, free of any world.
"""

from __future__ import annotations

from typing import Annotated

import msgspec

__all__ = [
    "ArenaEvent",
    "BoxesAdded",
    "BoxesRemoved",
    "LightMoves",
    "RobotsJoin",
    "RobotsLeave",
    "WallAppears",
    "check_events",
    "describe",
]

_Count = Annotated[int, msgspec.Meta(ge=1)]


class _Event(
    msgspec.Struct, forbid_unknown_fields=True, kw_only=True, frozen=True, tag_field="kind"
):
    #: the counted evaluation that is the first in the changed arena (1 .. ``evaluations``)
    evaluation: Annotated[int, msgspec.Meta(ge=1)] | None = None
    #: or: the run's served seconds (over its resumptions) after which the change happens
    seconds: Annotated[float, msgspec.Meta(ge=0.0)] | None = None
    #: what a person reads in the report beside the event (default: what it does)
    note: str = ""


class LightMoves(_Event, frozen=True, tag="light-moves"):
    """The lamp moves to ``position`` (x, y on the floor, metres); the arena needs a lamp."""

    position: tuple[float, float]


class BoxesAdded(_Event, frozen=True, tag="boxes-added"):
    """``count`` boxes appear at random free places in ``region`` (x0, y0, x1, y1; default the
    whole floor)."""

    count: _Count
    region: tuple[float, float, float, float] | None = None


class BoxesRemoved(_Event, frozen=True, tag="boxes-removed"):
    """``count`` boxes are taken away (the last placed first), or ``all`` of them."""

    count: _Count | None = None
    all: bool = False


class WallAppears(_Event, frozen=True, tag="wall-appears"):
    """An interior wall from ``start`` to ``end`` (x, y, metres; horizontal or vertical)."""

    start: tuple[float, float]
    end: tuple[float, float]


class RobotsLeave(_Event, frozen=True, tag="robots-leave"):
    """``count`` robots leave the swarm (the last of the roster first)."""

    count: _Count


class RobotsJoin(_Event, frozen=True, tag="robots-join"):
    """``count`` new robots join the swarm, placed at random free places."""

    count: _Count


#: One event of an experiment's ``events`` list, by its ``kind``.
ArenaEvent = LightMoves | BoxesAdded | BoxesRemoved | WallAppears | RobotsLeave | RobotsJoin


def describe(event: ArenaEvent) -> str:
    """What ``event`` does, in a few words (its ``note`` when it has one)."""
    if event.note:
        return event.note
    match event:
        case LightMoves(position=(x, y)):
            return f"the light moves to ({x:g}, {y:g})"
        case BoxesAdded(count=n):
            return f"{n} box{_es(n)} added"
        case BoxesRemoved(all=True):
            return "every box removed"
        case BoxesRemoved(count=int() as n):
            return f"{n} box{_es(n)} removed"
        case WallAppears(start=(x0, y0), end=(x1, y1)):
            return f"a wall appears from ({x0:g}, {y0:g}) to ({x1:g}, {y1:g})"
        case RobotsLeave(count=n):
            return f"{n} robot{_s(n)} leave{_s(1 if n > 1 else 2)}"
        case RobotsJoin(count=n):
            return f"{n} robot{_s(n)} join{_s(1 if n > 1 else 2)}"
    raise AssertionError(f"unknown event {event!r}")


def _s(n: int) -> str:
    return "" if n == 1 else "s"


def _es(n: int) -> str:
    return "" if n == 1 else "es"


def check_events(events: list[ArenaEvent], evaluations: int | None, robots: int) -> None:
    """Raise ValueError naming the key (``events[2].evaluation``) of the first event that
    cannot happen in an experiment of ``evaluations`` counted evaluations (None: endless) and
    ``robots`` robots; what needs the arena is :func:`simulator.events.check_arena_events`'s."""
    swarm = robots
    for i, event in enumerate(events):
        key = f"events[{i}]"
        if (event.evaluation is None) == (event.seconds is None):
            raise ValueError(f"`{key}`: give either `evaluation` or `seconds`, not both or none")
        if evaluations is not None and (event.evaluation or 0) > evaluations:
            raise ValueError(
                f"`{key}.evaluation`: {event.evaluation} is beyond the run's "
                f"{evaluations} evaluations"
            )
        if isinstance(event, BoxesRemoved) and (event.count is None) == (not event.all):
            raise ValueError(f"`{key}.count`: give either `count` or `all: true`")
        if isinstance(event, WallAppears):
            (x0, y0), (x1, y1) = event.start, event.end
            if (x0 != x1) == (y0 != y1):
                raise ValueError(
                    f"`{key}.end`: a wall runs horizontally or vertically and has a length"
                )
        if isinstance(event, RobotsLeave):
            swarm -= event.count
            if swarm < 1:
                raise ValueError(
                    f"`{key}.count`: {event.count} robots cannot leave: the swarm would have "
                    f"{swarm} robots"
                )
        if isinstance(event, RobotsJoin):
            swarm += event.count
