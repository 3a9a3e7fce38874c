"""``surprise-master sim --engine fast``: the experiment on the compiled engine, no robots.

:class:`FastRun` is the master's run without the network: the same (1+1) evolution
(:class:`~minimize_surprise.evolution.OnePlusOne`, seeded alike), the same run directory
(configuration snapshot, exactly-once rows and checkpoints, best genome, post-evaluation traces,
simulation.json, report), the same arena reset before the post-evaluation; each evaluation runs on
:class:`sim_stub.engine.Swarm`, which does what the agents do in lockstep, in one compiled loop.
For the same experiment and seed it gives the rows and traces that ``--engine agents`` gives.

Commits are grouped: the rows counted since the last commit are appended and the checkpoint
written at most every :data:`COMMIT_INTERVAL` seconds (and at the end of each phase), so a run of
a thousand evaluations a minute does not spend its time in fsync; a stopped run loses at most
that much work.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Final

import numpy as np

from master_service.config import MasterConfig
from master_service.experiments.simulation_setup import (
    SimulatedRun,
    simulated_safety,
    world_config,
    write_box_track,
    write_simulation_file,
)
from master_service.master import Progress, RunSummary
from master_service.rundir import (
    EVALUATION_COLUMNS,
    RunDir,
    RunState,
    format_row,
)
from minimize_surprise.config import ExperimentConfig
from minimize_surprise.errors import FileWriteError
from minimize_surprise.evolution import OnePlusOne
from minimize_surprise.fitness import swarm_fitness
from minimize_surprise.network import GenomeLayout, spec_from_config
from minimize_surprise.safety import dominance_warning
from minimize_surprise.wire import EvaluationStats, Result, Trace
from sim_stub.engine import EvaluationRecord, Swarm
from sim_stub.world import box_frame_steps

__all__ = ["COMMIT_INTERVAL", "FastRun"]

#: Seconds between two commits at most: a stopped run repeats at most this much of its work.
COMMIT_INTERVAL: Final = 2.0


class FastRun:
    """One experiment on the engine, into a run directory (see the module docstring).

    ``on_progress`` sees a :class:`~master_service.master.Progress` after every evaluation.
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
        self.genome_size = GenomeLayout(self.spec).size
        self.swarm = Swarm(
            world_config(experiment), simulated_safety(experiment), self.spec, experiment.seed
        )
        self.ids = list(self.swarm.ids)
        self.config = MasterConfig(
            experiment=experiment, host="127.0.0.1", port=0, allowed_robots=self.ids
        )
        self._boxes_before: list[list[float]] | None = None

    def run(
        self,
        run_dir: str | Path,
        *,
        plots: bool = True,
        resume: bool = False,
        should_stop: Callable[[], bool] | None = None,
    ) -> SimulatedRun | None:
        """Evolve, post-evaluate and report into ``run_dir``; the run and its metrics.

        A new run needs ``run_dir`` new or empty; with ``resume`` it continues the run there from
        its checkpoint (the simulated swarm as it was at that commit), to the result it would
        have reached without the stop. ``should_stop`` is asked between evaluations: once it
        answers true the run commits and returns None (resume it later). Without ``plots`` the
        report writes its metrics but draws nothing.
        """
        from master_service.reporting.report import write_report  # matplotlib: only when reporting

        directory = RunDir(run_dir)
        state = self._open(directory, resume)
        log = _run_log(directory)
        stop = should_stop or (lambda: False)
        try:
            if resume:
                log.info("resumed: %d evaluations done", state.optimizer.evaluations)
            started = time.monotonic() - state.elapsed_s
            if state.phase == "evolution" and not self._evolve(
                directory, state, log, started, stop
            ):
                return None
            post = self._post_evaluate(directory, state, log, started)
        except FileWriteError as exc:
            # Into master.log if it still takes lines; the command line says it on the console.
            log.error("the run stopped: %s; it can be resumed", exc)
            raise
        finally:
            directory.close()
            directory.close_log(log)
        self._write_simulation_file(directory.path)
        opt = state.optimizer
        summary = RunSummary(
            run_dir=directory.path,
            evaluations=opt.evaluations,
            best_fitness=opt.best_fitness,
            best_genome=None if opt.best is None else opt.best.copy(),
            failed_attempts=0,
            post_evaluation_fitness=post,
        )
        return SimulatedRun(summary, write_report(directory.path, plots=plots))

    def _open(self, directory: RunDir, resume: bool) -> RunState:
        """The run's state: new (the directory created) or the checkpoint's (restored)."""
        experiment = self.experiment
        state = None
        if resume:
            directory.check_experiment(experiment)
            state = directory.read_state(self.config)
        else:
            directory.create(self.config)
            self._write_simulation_file(directory.path)
        if state is None:  # new, or stopped before its first commit
            optimizer = OnePlusOne(experiment.evolution, self.genome_size, experiment.seed)
            return RunState(
                run_id=directory.path.resolve().name, optimizer=optimizer, roster=self.ids
            )
        directory.prepare_resume(state)
        if state.simulation is not None:
            self.swarm.restore(state.simulation)
        return state

    # -- the phases ------------------------------------------------------------------------------

    def _evolve(
        self,
        directory: RunDir,
        state: RunState,
        log: logging.Logger,
        started: float,
        stop: Callable[[], bool],
    ) -> bool:
        """Count evaluations until done (True) or told to stop (False, committed)."""
        experiment = self.experiment
        opt = state.optimizer
        total = experiment.evolution.evaluations
        header = [*EVALUATION_COLUMNS, *(f"fitness_{robot}" for robot in self.ids)]
        rows: list[str] = []
        best_changed = False
        last_commit = time.monotonic()
        while not opt.done:
            if stop():
                self._commit(directory, state, rows, header, best_changed, started)
                log.info("stopped after %d evaluations", opt.evaluations)
                return False
            candidate = opt.ask()
            state.next_evaluation_id += 1
            state.attempts += 1
            began = time.monotonic()
            record = self.swarm.evaluate(candidate.genome, experiment.evaluation_steps)
            fitnesses = [float(f) for f in record.fitness]
            outcome = opt.tell(swarm_fitness(fitnesses))
            duration = time.monotonic() - began
            share = record.safety_share(experiment.evaluation_steps)
            rows.append(
                format_row(
                    outcome.evaluation,
                    outcome.kind,
                    outcome.fitness,
                    outcome.best_fitness,
                    outcome.accepted,
                    state.attempts,
                    duration,
                    share,
                    fitnesses,
                )
            )
            state.attempts = 0
            best_changed |= outcome.accepted
            log.info(
                "evaluation %d/%d %s: fitness %.4f, best %.4f%s, safety %.0f %%",
                outcome.evaluation,
                total,
                outcome.kind,
                outcome.fitness,
                outcome.best_fitness,
                ", accepted" if outcome.accepted and outcome.kind == "offspring" else "",
                100 * share,
            )
            if opt.done:
                state.phase = "post-evaluation" if experiment.post_evaluation_steps else "done"
            if opt.done or time.monotonic() - last_commit >= COMMIT_INTERVAL:
                self._commit(directory, state, rows, header, best_changed, started)
                rows, best_changed, last_commit = [], False, time.monotonic()
            self._emit(state, outcome.fitness, started, share)
        return True

    def _post_evaluate(
        self, directory: RunDir, state: RunState, log: logging.Logger, started: float
    ) -> float | None:
        if state.phase != "post-evaluation":
            return None
        opt = state.optimizer
        assert opt.best is not None
        steps = self.experiment.post_evaluation_steps
        evaluation_id = state.next_evaluation_id
        state.next_evaluation_id += 1
        # The paper's post-evaluation starts from a fresh arena, as --engine agents does.
        world = self.swarm.world
        world.reset(seed=self.experiment.seed + 1)
        self._boxes_before = world.box_positions.tolist()
        log.info("post-evaluation of the best genome for %d steps", steps)
        record = self.swarm.evaluate(opt.best, steps, record=True)
        results = {
            robot: _result(evaluation_id, record, index, steps)
            for index, robot in enumerate(self.ids)
        }
        directory.write_post_evaluation(evaluation_id, opt.best_fitness, steps, results)
        assert record.boxes is not None
        write_box_track(directory.path, record.boxes, box_frame_steps(world.config.dt))
        fitness = swarm_fitness([r.fitness for r in results.values()])
        share = record.safety_share(steps)
        log.info(
            "post-evaluation done: swarm fitness %.4f, safety drove %.0f %% of the steps",
            fitness,
            100 * share,
        )
        warning = dominance_warning(share, record.interventions)
        if warning is not None:
            log.warning("post-evaluation: %s", warning)
        state.phase = "done"
        self._commit(directory, state, [], [], False, started)
        self._emit(state, None, started, None)
        return fitness

    # -- bookkeeping -----------------------------------------------------------------------------

    def _commit(
        self,
        directory: RunDir,
        state: RunState,
        rows: list[str],
        header: list[str],
        best_changed: bool,
        started: float,
    ) -> None:
        state.csv_rows += len(rows)
        state.elapsed_s = time.monotonic() - started
        state.simulation = self.swarm.snapshot()  # between evaluations: consistent
        directory.commit(state.to_json(), "".join(rows) or None, header)
        opt = state.optimizer
        if best_changed and opt.best is not None:
            directory.write_best(opt.best, opt.best_fitness, opt.best_evaluation, self.spec)

    def _emit(
        self, state: RunState, last: float | None, started: float, share: float | None
    ) -> None:
        if self.on_progress is None:
            return
        opt = state.optimizer
        elapsed = time.monotonic() - started
        total = self.experiment.evolution.evaluations
        left = None
        if opt.evaluations and state.phase != "done":
            per = elapsed / opt.evaluations
            post = self.experiment.post_evaluation_steps / self.experiment.evaluation_steps
            left = per * (total - opt.evaluations + post)
        self.on_progress(
            Progress(
                run_id=state.run_id,
                phase=state.phase,
                waiting=False,
                evaluations=opt.evaluations,
                total=total,
                best_fitness=opt.best_fitness,
                last_fitness=last,
                robots_connected=len(self.ids),
                robots_expected=len(self.ids),
                failed_attempts=0,
                elapsed_s=elapsed,
                time_left_s=0.0 if state.phase == "done" else left,
                safety_share=share,
            )
        )

    def _write_simulation_file(self, run_dir: Path) -> None:
        write_simulation_file(
            run_dir,
            self.experiment,
            self.swarm.world,
            engine="fast",
            boxes_before=self._boxes_before,
        )


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
    directory.open_log(log)
    log.setLevel(logging.INFO)
    log.propagate = False
    return log
