"""What an evolution run drives and what it reports (docs/runs.md).

An :class:`Evaluator` evaluates one genome on the whole swarm and answers an :class:`Evaluation`;
:class:`master_service.evolution_run.EvolutionRun` drives it and reports :class:`Progress` while
it runs and a :class:`RunSummary` at the end. Kept apart from the loop so that displays and
evaluators import these plain types without the loop.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from master_service.rundir import RunDir, RunState
from minimize_surprise.events import ArenaEvent
from minimize_surprise.wire import EvaluationStats, Result
from runfiles.schema import Phase

__all__ = ["ArenaChange", "Evaluation", "Evaluator", "Progress", "RunSummary"]


@dataclass(frozen=True)
class Progress:
    """Where a run stands; handed to progress listeners on every change.

    ``phase`` is the checkpoint's phase; ``waiting`` is true while the swarm is incomplete.
    ``time_left_s`` is an estimate (None when unknown).
    """

    run_id: str
    phase: Phase
    waiting: bool
    evaluations: int
    #: the evaluations planned (None: an endless run)
    total: int | None
    best_fitness: float | None
    last_fitness: float | None
    robots_connected: int
    robots_expected: int
    failed_attempts: int
    elapsed_s: float
    time_left_s: float | None
    #: share of the last counted evaluation's steps in which the safety layer drove
    safety_share: float | None = None
    #: why the run waits for a person (batteries to swap, robots to place), None while it runs
    paused: str | None = None


@dataclass(frozen=True)
class RunSummary:
    """What a finished run returns (:meth:`EvolutionRun.run`)."""

    run_dir: Path
    evaluations: int
    best_fitness: float | None
    best_genome: np.ndarray | None
    failed_attempts: int
    post_evaluation_fitness: float | None


@dataclass(frozen=True)
class Evaluation:
    """One attempt at evaluating a genome on the swarm, as an :class:`Evaluator` reports it.

    ``failure`` is None when every robot answered (the attempt counts) and says why otherwise.
    ``fitnesses`` are the robots' in the order of ``robots``; ``results`` holds every robot's
    :class:`~minimize_surprise.wire.Result` for a recorded attempt (its trace). ``seconds`` is
    the attempt's duration, ``safety_share`` the share of the robots' steps the safety layer drove.
    ``stats`` are the robots' own statistics in the order of ``robots`` (overruns, read failures,
    battery), empty where the evaluator has none to report (the compiled engine). ``started_at``
    is the wall-clock time the attempt went out to the robots (None: no robots to tell).
    """

    evaluation_id: int
    robots: tuple[str, ...]
    failure: str | None
    fitnesses: Sequence[float] = ()
    seconds: float = 0.0
    safety_share: float = 0.0
    results: dict[str, Result] | None = None
    stats: Sequence[EvaluationStats] = ()
    started_at: float | None = None


@dataclass(frozen=True)
class ArenaChange:
    """What an evaluator did for one of the experiment's events: ``detail`` in a line, and the
    robots that ``left`` and ``joined`` the swarm (``robots-leave``, ``robots-join``)."""

    detail: str
    left: tuple[str, ...] = ()
    joined: tuple[str, ...] = ()


class Evaluator(Protocol):
    """What an :class:`EvolutionRun` drives: evaluations of one genome on the whole swarm.

    ``reports_robot_stats`` is true for real robots (or agents standing in for them): their
    overruns, read failures and batteries get columns in ``evaluations.csv``.
    """

    reports_robot_stats: bool

    @property
    def robots_connected(self) -> int:
        """Robots able to evaluate now."""

    @property
    def robots_expected(self) -> int:
        """Robots the swarm has."""

    @property
    def waiting(self) -> bool:
        """True while the run waits for robots (the swarm incomplete)."""

    def missing_robots(self) -> list[str]:
        """The swarm's robots not able to evaluate now."""

    async def swarm(self, state: RunState) -> list[str]:
        """Wait until every robot of the swarm can evaluate; its robots, in a fixed order. The
        first time, fix the swarm in ``state.roster``."""

    async def evaluate(
        self, evaluation_id: int, genome: np.ndarray, steps: int, *, record: bool
    ) -> Evaluation:
        """Evaluate ``genome`` on ``robots`` for ``steps`` control steps."""

    async def before_post_evaluation(self) -> None:
        """Called before each attempt of the post-evaluation, every robot idle (a simulator
        resets its arena here, as the paper does before this run)."""

    async def after_post_evaluation(self, run_dir: RunDir) -> None:
        """Called once the post-evaluation's traces are written into ``run_dir``."""

    def snapshot(self) -> dict[str, Any] | None:
        """A simulator's state, kept in every checkpoint so a resumed run goes on exactly;
        None for real robots. Called between evaluations, every robot idle."""

    async def change_arena(self, event: ArenaEvent, index: int) -> ArenaChange | None:
        """Make the experiment's event ``index`` happen, between evaluations (a simulator
        changes its world); None where a person must make it (real robots: the run pauses)."""
