"""A swarm that loses a robot for good: when a robot counts as gone, and what a change is.

The pieces the master (:mod:`master_service.master`), the evolution loop
(:mod:`master_service.evolution_run`) and the swap's desk (:mod:`master_service.swap`) share,
free of their I/O: :class:`AwayClock` times each robot's absence against ``robot_gone_after``,
:func:`changed` makes one :class:`~runfiles.schema.SwarmChange`, and the lines a person reads.
docs/runs.md, "A robot lost for good", tells the whole story.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from pathlib import Path

from runfiles.schema import EVENT_SWARM_CHANGE, Event, SwarmChange

__all__ = ["AwayClock", "changed", "changes_text", "dropped_event", "gone_text"]


class AwayClock:
    """Since when (monotonic seconds) each robot of the swarm has been away; one away for
    ``limit`` seconds or longer is gone for good (``limit`` None: never)."""

    def __init__(self, limit: float | None) -> None:
        self.limit = limit
        self._since: dict[str, float] = {}

    def start(self, robots: Iterable[str]) -> None:
        """Count ``robots`` away from now on (a resumed swarm's, before they reconnect)."""
        now = time.monotonic()
        self._since = dict.fromkeys(robots, now)

    def left(self, robot: str, roster: Sequence[str] | None) -> None:
        """``robot`` left; counted when it is of the swarm ``roster``, from its first leaving."""
        if roster is not None and robot in roster:
            self._since.setdefault(robot, time.monotonic())

    def back(self, robot: str) -> None:
        """``robot`` is connected again, or no longer in the swarm."""
        self._since.pop(robot, None)

    def restart(self, robots: Iterable[str]) -> None:
        """Count ``robots`` away from now on again: a person let the run wait on for them."""
        now = time.monotonic()
        for robot in robots:
            self._since[robot] = now

    def gone(self, missing: Sequence[str]) -> tuple[list[str], float, float | None]:
        """Of the swarm's ``missing`` robots, those gone for good; how long the first of them
        has been away; and the seconds until the next one will be gone (None: none will)."""
        if self.limit is None:
            return [], 0.0, None
        now = time.monotonic()
        gone, wake_in = [], None
        for robot in missing:
            left = self._since.setdefault(robot, now) + self.limit - now
            if left <= 0:
                gone.append(robot)
            else:
                wake_in = left if wake_in is None else min(wake_in, left)
        away = max((now - self._since[robot] for robot in gone), default=0.0)
        return gone, away, wake_in


def changed(
    roster: Sequence[str], left: str, joined: str | None, from_evaluation: int
) -> SwarmChange:
    """The change that takes ``left`` out of ``roster`` from counted evaluation
    ``from_evaluation`` on, ``joined`` in its place (None: nobody). Raises ValueError when
    ``left`` is not in the swarm or ``joined`` is."""
    robots = list(roster)
    if left not in robots:
        raise ValueError(f"{left} is not in the swarm")
    if joined is None:
        robots.remove(left)
    elif joined in robots:
        raise ValueError(f"{joined} is in the swarm already")
    else:
        robots[robots.index(left)] = joined
    return SwarmChange(
        from_evaluation=from_evaluation, robots=robots, left=left, joined=joined, time=time.time()
    )


def gone_text(gone: Sequence[str], away_s: float, run_dir: Path) -> str:
    """The robot-gone pause's line: who, for how long, and the command that brings a spare."""
    spare = "SPARE" if len(gone) == 1 else "SPARE (one robot at a time)"
    return (
        f"{', '.join(gone)} gone for {away_s:.0f} s: bring in a spare with `surprise-master "
        f"swap {run_dir} {gone[0]} {spare}`, or get it back"
    )


def dropped_event(change: SwarmChange, away_s: float, minimum: int) -> Event:
    """The ``swarm-change`` event of a robot the run goes on without (``min_robots``), its
    ``detail`` the log's line."""
    return Event(
        time=change.time,
        kind=EVENT_SWARM_CHANGE,
        robot=change.left,
        accepted=True,
        evaluation_id=change.from_evaluation,
        detail=(
            f"robot {change.left} gone for {away_s:.0f} s: the run goes on without it from "
            f"evaluation {change.from_evaluation}, with {len(change.robots)} robots "
            f"(min_robots {minimum})"
        ),
    )


def changes_text(changes: Sequence[SwarmChange]) -> str:
    """How the swarm changed, for the log line of a (resumed) run's start; empty if never."""
    if not changes:
        return ""
    last = changes[-1]
    count = f"{len(changes)} change{'s' if len(changes) > 1 else ''}"
    return f" ({', '.join(last.robots)} since evaluation {last.from_evaluation}, after {count})"
