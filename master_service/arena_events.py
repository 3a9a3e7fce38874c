"""When an experiment's events are due, and the lines they leave (docs/changing-arenas.md).

The evolution loop asks :func:`due_events` between two evaluations; each due event is made to
happen by the evaluator (a simulator changes its world) or, on real robots, by a person while
the run pauses (:func:`person_text`), and is then logged as an ``arena-change`` event
(:func:`arena_event`). The checkpoint lists the events that happened, so a resumed run never
makes one happen twice.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

from minimize_surprise.events import ArenaEvent, RobotsLeave, describe
from runfiles.schema import EVENT_ARENA, Event

__all__ = ["arena_event", "due_events", "leaving", "person_text"]


def due_events(
    events: Sequence[ArenaEvent], applied: Sequence[int], evaluations: int, elapsed_s: float
) -> list[int]:
    """The indexes of ``events`` due before the next evaluation and not yet ``applied``, in the
    order they happen: after ``evaluations`` counted evaluations, the run served ``elapsed_s``
    seconds."""
    done = set(applied)
    due = []
    for index, event in enumerate(events):
        if index in done:
            continue
        if (event.evaluation is not None and event.evaluation <= evaluations + 1) or (
            event.seconds is not None and event.seconds <= elapsed_s
        ):
            due.append(index)
    return sorted(due, key=lambda i: (events[i].evaluation or 0, events[i].seconds or 0.0, i))


def arena_event(index: int, detail: str, evaluations: int, elapsed_s: float) -> Event:
    """The ``arena-change`` line of the experiment's event ``index``, made after
    ``evaluations`` counted evaluations."""
    return Event(
        time=time.time(),
        kind=EVENT_ARENA,
        index=index,
        accepted=True,
        evaluation=evaluations,
        seconds=round(elapsed_s, 3),
        detail=detail,
    )


def leaving(event: ArenaEvent, roster: Sequence[str]) -> tuple[str, ...]:
    """The robots a ``robots-leave`` event takes out of ``roster`` (the last ones; at least one
    stays); none for any other event."""
    if not isinstance(event, RobotsLeave):
        return ()
    return tuple(roster[len(roster) - min(event.count, len(roster) - 1) :])


def person_text(event: ArenaEvent, index: int, run_dir: Path) -> str:
    """The pause's line on real robots: what to change, and how to go on."""
    what = describe(event)
    if isinstance(event, RobotsLeave):
        what += " (the last of the swarm: take them off the arena)"
    return (
        f"event {index} of the experiment: {what}; make the change in the arena, "
        f"then `surprise-master continue {run_dir}`"
    )
