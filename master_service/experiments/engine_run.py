"""``surprise-master sim --engine fast``: the experiment on the compiled engine, no robots.

:class:`FastRun` is the master's run without the network: the same evolution loop
(:class:`~master_service.evolution_run.EvolutionRun`: the (1+1) evolution seeded alike, the same
run directory with its configuration snapshot, exactly-once rows and checkpoints, best genome and
post-evaluation traces, resume), the same arena reset before the post-evaluation, then
simulation.json and the report. Its evaluator runs each evaluation on
:class:`simulator.engine.Swarm`, which does what the agents do in lockstep, in one compiled loop.
For the same experiment and seed it gives the rows and traces that ``--engine agents`` gives.

Evaluation ids never leave the process here, so commits are grouped: the rows counted since the
last commit are appended and the checkpoint written at most every :data:`COMMIT_INTERVAL`
seconds (and at the end of each phase), so a run of a thousand evaluations a minute does not
spend its time in fsync; a stopped run loses at most that much work.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, NamedTuple

import numpy as np

from master_service.config import MasterConfig
from master_service.evaluation import ArenaChange, Evaluation, Progress, RunSummary
from master_service.evolution_run import EvolutionRun
from master_service.experiments.simulation_setup import (
    SimulatedRun,
    simulated_safety,
    world_config,
    write_box_track,
    write_simulation_file,
)
from master_service.replay import ReplaySource, write_replay_file
from master_service.rundir import RunDir, RunState
from minimize_surprise import precompile
from minimize_surprise.config import ExperimentConfig
from minimize_surprise.events import ArenaEvent, describe
from minimize_surprise.network import spec_from_config
from minimize_surprise.wire import EvaluationStats, Result, Trace
from simulator import metrics
from simulator.engine import EvaluationRecord, Swarm, compile_plan, evaluate_swarms
from simulator.events import apply_to_world, check_arena_events, event_rng
from simulator.world import box_frame_steps

__all__ = ["COMMIT_INTERVAL", "EngineEvaluator", "FastRun", "SwarmBatcher", "run_batch"]

#: Seconds between two commits at most: a stopped run repeats at most this much of its work.
COMMIT_INTERVAL: Final = 2.0


class FastRun:
    """One experiment on the engine, into a run directory (see the module docstring).

    ``on_progress`` sees a :class:`~master_service.evolution_run.Progress` on every change.
    """

    def __init__(
        self,
        experiment: ExperimentConfig,
        *,
        on_progress: Callable[[Progress], None] | None = None,
    ) -> None:
        self.experiment = experiment
        self.on_progress = on_progress
        self.spec = spec_from_config(experiment)
        world = world_config(experiment)
        check_arena_events(experiment.events, world)
        self.swarm = Swarm(world, simulated_safety(experiment), self.spec, experiment.seed)
        self.evaluator = EngineEvaluator(self.swarm, experiment)
        self.ids = self.evaluator.ids
        # The configuration snapshot of the run directory: what the master of ``--engine
        # agents`` would hold for this swarm (config.yaml has one format for both engines).
        self.config = MasterConfig(
            experiment=experiment, host="127.0.0.1", port=0, allowed_robots=self.ids
        )

    def compile_ahead(self) -> int:
        """Compile the kernels this run calls on every core at once, then the engine's loop
        around them while the helpers compile the lists it takes and the report's measures
        (:func:`~minimize_surprise.precompile.compile_ahead`); the number of processes that
        compiled, 0 when everything was compiled already."""
        plan = compile_plan(self.swarm)
        return precompile.compile_ahead(
            plan.kernels, then=plan.lists + metrics.compile_plan(), last=plan.loop
        )

    def run(
        self,
        run_dir: str | Path,
        *,
        plots: bool = True,
        resume: bool = False,
        should_stop: Callable[[], bool] | None = None,
        replay: ReplaySource | None = None,
    ) -> SimulatedRun | None:
        """Evolve, post-evaluate and report into ``run_dir``; the run and its metrics.

        A new run needs ``run_dir`` new or empty; with ``resume`` it continues the run there from
        its checkpoint (the simulated swarm as it was at that commit), to the result it would
        have reached without the stop. ``should_stop`` is asked between evaluations: once it
        answers true the run commits and returns None (resume it later). Without ``plots`` the
        report writes its metrics but draws nothing. ``replay`` (a new run only) post-evaluates
        that genome instead of evolving one (:mod:`master_service.replay`).
        """
        opened = self._open(run_dir, resume=resume, replay=replay)
        try:
            # The loop logs a failed write into master.log; the command line says it too.
            summary = asyncio.run(opened.run(should_stop))
        finally:
            opened.close()
        return self._finish(opened, summary, plots)

    def _open(
        self, run_dir: str | Path, *, resume: bool, replay: ReplaySource | None = None
    ) -> _OpenRun:
        # The run directory opened and the evolution loaded, ready to run.
        directory = RunDir(run_dir)
        log = _run_log(directory)
        evolution = EvolutionRun(
            self.config,
            directory,
            self.spec,
            self.evaluator,
            log,
            ids_leave_process=False,
            commit_interval=COMMIT_INTERVAL,
        )
        if self.on_progress is not None:
            evolution.add_progress_listener(self.on_progress)
        opened = _OpenRun(directory, log, evolution)
        try:
            state = evolution.load(resume=resume, roster=self.ids, replay=replay)
            evolution.open(resume=resume)
            if replay is not None and not resume:
                write_replay_file(directory, replay)
            if replay is not None:
                self.evaluator.replay_safety = replay.safety_for(len(self.ids))
            if not resume:
                self._write_simulation_file(directory.path)
            elif state.simulation is not None:
                # The events that happened change the world's set-up (a lamp, the swarm's
                # size); the snapshot then gives its state.
                for index in state.events_applied:
                    self.evaluator.apply(self.experiment.events[index], index)
                self.swarm.restore(state.simulation)
            if resume:
                log.info("resumed: %d evaluations done", state.optimizer.evaluations)
        except BaseException:
            opened.close()
            raise
        return opened

    def _finish(
        self, opened: _OpenRun, summary: RunSummary | None, plots: bool
    ) -> SimulatedRun | None:
        # After the loop: simulation.json and the report of a finished run.
        from reporting.report import write_report  # matplotlib: only when reporting

        if summary is None:
            return None
        path = opened.directory.path
        self._write_simulation_file(path)
        return SimulatedRun(summary, write_report(path, plots=plots))

    def _write_simulation_file(self, run_dir: Path) -> None:
        write_simulation_file(
            run_dir,
            self.experiment,
            self.swarm.world,
            engine="fast",
            boxes_before=self.evaluator.boxes_before,
            safety_before=self.evaluator.safety_before,
        )


class EngineEvaluator:
    """The engine as an :class:`~master_service.evaluation.Evaluator`: a whole swarm's
    evaluation in one compiled call; its robots are always there."""

    #: The engine keeps neither overruns nor read failures, and has no batteries.
    reports_robot_stats = False

    def __init__(self, swarm: Swarm, experiment: ExperimentConfig) -> None:
        self.engine = swarm
        self.experiment = experiment
        self.ids = list(swarm.ids)
        #: the boxes where the post-evaluation's arena put them (None before it)
        self.boxes_before: list[list[float]] | None = None
        #: every robot's safety state when the post-evaluation began (None before it)
        self.safety_before: list[list[int]] | None = None
        #: a replay's: the safety states its source's post-evaluation began with
        self.replay_safety: list[list[int]] | None = None
        self._recorded: EvaluationRecord | None = None
        #: evaluates this run's swarm with other runs' in one compiled call (None: alone)
        self.batcher: SwarmBatcher | None = None

    @property
    def robots_connected(self) -> int:
        """Every simulated robot, always."""
        return len(self.ids)

    @property
    def robots_expected(self) -> int:
        """The swarm's size."""
        return len(self.ids)

    @property
    def waiting(self) -> bool:
        """Never: the simulated robots are always there."""
        return False

    def missing_robots(self) -> list[str]:
        """None."""
        return []

    async def swarm(self, state: RunState) -> list[str]:
        """The simulated robots (fixed when the run began)."""
        if state.roster is None:
            state.roster = list(self.ids)
        return state.roster

    async def evaluate(
        self, evaluation_id: int, genome: np.ndarray, steps: int, *, record: bool
    ) -> Evaluation:
        """One evaluation on the engine (it never fails: no robot can drop out); with a
        :attr:`batcher`, in one call with the other runs' evaluations, its time the batch's
        divided among them."""
        if self.batcher is not None:
            record_, seconds = await self.batcher.evaluate(self.engine, genome, steps, record)
        else:
            began = time.monotonic()
            record_ = self.engine.evaluate(genome, steps, record=record)
            seconds = time.monotonic() - began
        fitnesses = [float(f) for f in record_.fitness]
        results = None
        if record:
            self._recorded = record_
            results = {
                robot: _result(evaluation_id, record_, index, steps)
                for index, robot in enumerate(self.ids)
            }
        return Evaluation(
            evaluation_id,
            tuple(self.ids),
            None,
            fitnesses=fitnesses,
            seconds=seconds,
            safety_share=record_.safety_share(steps),
            results=results,
        )

    async def before_post_evaluation(self) -> None:
        """The paper's post-evaluation starts from a fresh arena, as ``--engine agents`` does."""
        world = self.engine.world
        world.reset(seed=self.experiment.seed + 1)
        self.boxes_before = world.box_positions.tolist()
        if self.replay_safety is not None:
            self.engine.safety[:] = np.array(self.replay_safety, dtype=np.int64)
        self.safety_before = self.engine.safety.tolist()

    async def after_post_evaluation(self, run_dir: RunDir) -> None:
        """The boxes' track beside the traces (the report's animation)."""
        assert self._recorded is not None and self._recorded.boxes is not None
        frames = box_frame_steps(self.engine.world.config.dt)
        await asyncio.to_thread(write_box_track, run_dir.path, self._recorded.boxes, frames)

    def snapshot(self) -> dict[str, Any]:
        """The world and the safety layers (between evaluations: consistent)."""
        return self.engine.snapshot()

    async def change_arena(self, event: ArenaEvent, index: int) -> ArenaChange:
        """The experiment's event ``index`` happens to the engine's world
        (:mod:`simulator.events`)."""
        return self.apply(event, index)

    def apply(self, event: ArenaEvent, index: int) -> ArenaChange:
        """:meth:`change_arena`, also called to set a resumed run's world up as it was."""
        rng = event_rng(self.experiment.seed, index)
        keep, joined = apply_to_world(self.engine.world, event, rng)
        left, new = self.engine.resize(keep, joined)
        self.ids = list(self.engine.ids)
        return ArenaChange(describe(event), tuple(left), tuple(new))


@dataclass
class _OpenRun:
    """A run whose directory is open: its loop, and what :meth:`close` releases."""

    directory: RunDir
    log: logging.Logger
    evolution: EvolutionRun

    async def run(self, should_stop: Callable[[], bool] | None) -> RunSummary | None:
        try:
            return await self.evolution.run(should_stop)
        finally:
            await self.evolution.close()

    def close(self) -> None:
        self.directory.close()
        self.directory.close_log(self.log)


def _result(evaluation_id: int, record: EvaluationRecord, robot: int, steps: int) -> Result:
    """Robot ``robot``'s recorded result, as its agent would have sent it."""
    assert record.sensors is not None and record.poses is not None
    trace = Trace.from_arrays(
        sensors=record.sensors[:, robot],
        predictions=record.predictions[:, robot],  # type: ignore[index]
        actions=record.actions[:, robot],  # type: ignore[index]
        commands=record.commands[:, robot],  # type: ignore[index]
        safety=record.safety_reasons(robot),
        poses=record.poses[:, robot],
    )
    stats = EvaluationStats(
        steps_run=steps, overruns=0, interventions=record.interventions[robot], read_failures=0
    )
    return Result(
        evaluation_id=evaluation_id,
        fitness=float(np.float64(record.fitness[robot])),
        stats=stats,
        trace=trace,
    )


def _run_log(directory: RunDir) -> logging.Logger:
    # The run's own logger writing master.log, as the master's does.
    log = logging.getLogger(f"master_service.run.{directory.path.resolve().name}")
    log.setLevel(logging.INFO)
    log.propagate = False
    return log


class _Request(NamedTuple):
    """One run's evaluation waiting for the others of its batch."""

    swarm: Swarm
    genome: np.ndarray
    steps: int
    record: bool
    future: asyncio.Future[tuple[EvaluationRecord, float]]


class SwarmBatcher:
    """Evaluates the swarms of ``runs`` runs of one event loop together: each run's evaluation
    waits until every run still going has asked for one, then all run in one compiled call
    (:func:`~simulator.engine.evaluate_swarms`), grouped by length and recording. A run that
    ends says so (:meth:`run_ended`) so the others no longer wait for it. Each swarm's results
    are those it has alone, to the last bit."""

    def __init__(self, runs: int) -> None:
        self.live = runs
        self._pending: list[_Request] = []

    async def evaluate(
        self, swarm: Swarm, genome: np.ndarray, steps: int, record: bool
    ) -> tuple[EvaluationRecord, float]:
        """``swarm.evaluate(genome, steps, record=record)`` in a batch; with the seconds of the
        batch's call divided by its swarms."""
        future: asyncio.Future[tuple[EvaluationRecord, float]]
        future = asyncio.get_running_loop().create_future()
        self._pending.append(_Request(swarm, genome, steps, record, future))
        self._flush_if_complete()
        return await future

    def run_ended(self) -> None:
        """One run is over (done, stopped or failed): stop waiting for it."""
        self.live -= 1
        self._flush_if_complete()

    def _flush_if_complete(self) -> None:
        if not self._pending or len(self._pending) < self.live:
            return
        pending, self._pending = self._pending, []
        groups: dict[tuple[int, bool], list[_Request]] = {}
        for request in pending:
            groups.setdefault((request.steps, request.record), []).append(request)
        for (steps, record), requests in groups.items():
            began = time.monotonic()
            try:
                results = evaluate_swarms(
                    [r.swarm for r in requests], [r.genome for r in requests], steps,
                    record=record,
                )  # fmt: skip
            except Exception as exc:  # every run of the batch fails alike
                for request in requests:
                    request.future.set_exception(exc)
                continue
            share = (time.monotonic() - began) / len(requests)
            for request, result in zip(requests, results, strict=True):
                request.future.set_result((result, share))


def run_batch(
    runs: list[tuple[FastRun, Path]], *, plots: bool = False
) -> list[SimulatedRun | BaseException]:
    """Run new runs into their directories at once, their swarms evaluated together
    (:class:`SwarmBatcher`): one process, one compiled call per evaluation of them all. Each
    run is what it is alone (its seed, evolution, checkpoints, run directory and results, to the
    last bit); its outcome, or the exception that stopped it, in order. The runs' swarms must be
    compatible (:meth:`~simulator.engine.Swarm.check_batch`)."""
    for fast, _ in runs[1:]:
        runs[0][0].swarm.check_batch(fast.swarm)
    batcher = SwarmBatcher(len(runs))
    opened: list[_OpenRun | BaseException] = []
    for fast, run_dir in runs:
        fast.evaluator.batcher = batcher
        try:
            opened.append(fast._open(run_dir, resume=False))
        except Exception as exc:
            opened.append(exc)
            batcher.run_ended()

    async def one(run: _OpenRun) -> RunSummary | None:
        try:
            return await run.run(None)
        finally:
            batcher.run_ended()

    async def all_runs() -> list[Any]:
        live = [run for run in opened if isinstance(run, _OpenRun)]
        return await asyncio.gather(*(one(run) for run in live), return_exceptions=True)

    try:
        summaries = iter(asyncio.run(all_runs()))
    finally:
        for run in opened:
            if isinstance(run, _OpenRun):
                run.close()
    outcomes: list[SimulatedRun | BaseException] = []
    for (fast, _), run in zip(runs, opened, strict=True):
        if isinstance(run, BaseException):
            outcomes.append(run)
            continue
        summary = next(summaries)
        if isinstance(summary, BaseException):
            outcomes.append(summary)
            continue
        try:
            finished = fast._finish(run, summary, plots)
        except Exception as exc:
            outcomes.append(exc)
            continue
        assert finished is not None, "a run of a batch is never told to stop"
        outcomes.append(finished)
    return outcomes
