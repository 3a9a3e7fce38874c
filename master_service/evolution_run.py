"""One run of (1+1) online evolution, whatever evaluates its genomes: the loop written once.

:class:`EvolutionRun` owns everything around ask and tell (docs/runs.md): the run's state and its
checkpoint, the exactly-once commits of ``evaluations.csv`` and ``checkpoint.json``, resume,
retries of an evaluation that did not count, progress and its estimate of the time left, the log
lines, and the post-evaluation of the best genome with its traces. What evaluates a genome is an
:class:`Evaluator`: the robots over TCP (:class:`master_service.master.Master`) or the compiled
engine (:class:`master_service.experiments.engine_run.FastRun`); the loop knows nothing of how.

Commits. Each writes the rows counted since the last one and the checkpoint in a worker thread
while the next evaluation runs, once the previous one is on disk. Where ids leave this process
(``ids_leave_process``: robots hear them) each attempt's id is committed before it goes out and a
resumed run skips one id: an id is never reused (see :mod:`master_service.master`). Where they do
not (the engine), commits come at most every ``commit_interval`` seconds, so a thousand
evaluations a minute do not spend their time in fsync; a stopped run repeats at most that much.

Why one file of over 600 lines: :class:`EvolutionRun` is one object, the loop and the state its
commits write; what could stand alone already does (pauses, the swarm's changes, when the
arena's events are due: :mod:`master_service.arena_events`).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import statistics
import time
from collections.abc import Callable
from typing import Final

import numpy as np

from master_service.arena_events import arena_event, due_events, person_text
from master_service.config import MasterConfig
from master_service.evaluation import ArenaChange, Evaluation, Evaluator, Progress, RunSummary
from master_service.pause import Pause, PauseGate, low_batteries
from master_service.replay import ReplaySource, check_spec
from master_service.rundir import FILE_ONLY, RunDir, RunState
from master_service.swarm import changed, dropped_event, gone_text
from minimize_surprise.dominance import dominance, ground_at_start
from minimize_surprise.errors import FileWriteError
from minimize_surprise.events import describe
from minimize_surprise.evolution import OnePlusOne
from minimize_surprise.fitness import swarm_fitness
from minimize_surprise.network import GenomeLayout, NetworkSpec
from minimize_surprise.text import format_duration
from runfiles import schema
from runfiles.schema import (
    ROBOT_STAT_PREFIXES,
    PostEvaluation,
    SwarmChange,
    append_event,
    evaluation_header,
    render_row,
    row_cells,
    widen_header,
)

__all__ = ["ETA_WINDOW", "RETRY_PAUSE", "RETRY_PAUSE_MAX", "EvolutionRun"]

#: Pause before the third and later attempt of the same genome, doubling up to the cap. A robot
#: that fails at once (a broken sensor answers Failed immediately) would otherwise be retried in a
#: tight loop that fills the log while the lab looks for the fault.
RETRY_PAUSE: Final = 0.5
RETRY_PAUSE_MAX: Final = 10.0
#: Counted evaluations the time-left estimate averages over: recent enough to follow a robot that
#: became slow, long enough to smooth one retried round.
ETA_WINDOW: Final = 20


class EvolutionRun:
    """The (1+1) online evolution of one run into ``run_dir`` (see the module docstring).

    ``config`` is the master configuration the run directory's snapshot holds (its experiment
    inline). ``log`` is the run's logger (its ``master.log`` is opened by :meth:`open`).
    ``on_progress`` listeners (also :meth:`add_progress_listener`) see a :class:`Progress` on
    every change; ``on_change`` is called on every change too, before them.
    """

    def __init__(
        self,
        config: MasterConfig,
        run_dir: RunDir,
        spec: NetworkSpec,
        evaluator: Evaluator,
        log: logging.Logger,
        *,
        ids_leave_process: bool,
        commit_interval: float = 0.0,
        on_change: Callable[[], None] | None = None,
    ) -> None:
        assert config.experiment is not None, "the experiment must be loaded"
        self.config = config
        self.experiment = config.experiment
        self.run_dir = run_dir
        self.run_id = run_dir.path.resolve().name
        self.spec = spec
        self.genome_size = GenomeLayout(spec).size
        self.evaluator = evaluator
        self.log = log
        self.ids_leave_process = ids_leave_process
        self.commit_interval = commit_interval
        self.state: RunState | None = None
        self._resumed_checkpoint = False
        self._on_change = on_change
        self._listeners: list[Callable[[Progress], None]] = []
        self._write: asyncio.Future[None] | None = None
        # Rows by column, rendered at commit against the header then (a spare may widen it).
        self._rows: list[dict[str, str]] = []
        self._header: list[str] | None = None  # the CSV's as written (None: the swarm's, later)
        # Since the last commit the header widened (rewrite the file's), the swarm changed.
        self._widen = self._swarm_dirty = False
        self._best_changed = False
        self._last_commit = 0.0
        self._started_at = 0.0
        self._elapsed_before = 0.0
        self._last_counted_at: float | None = None
        self._intervals: collections.deque[float] = collections.deque(maxlen=ETA_WINDOW)
        self._last_fitness: float | None = None
        self._last_safety_share: float | None = None
        #: waits for a person between evaluations (master_service.pause)
        self.pauses = PauseGate(run_dir, log)
        #: wait for the robots to be placed before the post-evaluation (``--pause-before-post``)
        self.pause_before_post = False
        # Whether the CSV holds the robots' statistics: as its header says once written (a run
        # started before those columns keeps its shape), else as the evaluator reports.
        self._robot_stats = evaluator.reports_robot_stats

    # -- opening -----------------------------------------------------------------------------

    def load(
        self,
        *,
        resume: bool,
        roster: list[str] | None = None,
        replay: ReplaySource | None = None,
    ) -> RunState:
        """The run's state, read from the checkpoint (``resume``) or new, writing nothing yet.

        A new run needs its directory absent or empty. ``roster`` fixes a new run's swarm at
        once (a simulated swarm knows its robots). ``replay`` makes a new run a replay: no
        evolution, its genome post-evaluated (:mod:`master_service.replay`).
        """
        state = None
        if resume:
            self.run_dir.check_experiment(self.experiment)
            state = self.run_dir.read_state(self.config)
            if state is not None and self.ids_leave_process:
                # The attempt in flight when the run stopped may have used the checkpointed
                # counter: skip it.
                state.next_evaluation_id += 1
        else:
            self.run_dir.check_new()
        self._resumed_checkpoint = state is not None
        if state is None:
            experiment = self.experiment
            optimizer = OnePlusOne(experiment.evolution, self.genome_size, experiment.seed)
            state = RunState(run_id=self.run_id, optimizer=optimizer, roster=roster)
            if replay is not None:
                check_spec(replay, self.experiment)
                optimizer.best = replay.genome.copy()
                optimizer.best_fitness = replay.fitness
                optimizer.best_evaluation = 0  # found by no evaluation of this run
                state.phase = "post-evaluation"
            if resume and self.ids_leave_process:
                # A run stopped before its first commit may have sent id 0.
                state.next_evaluation_id = 1
        self.state = state
        return state

    def open(self, *, resume: bool) -> None:
        """Create the run directory (new) or repair it for going on (``resume``), open the
        run's log and write the best genome so far; after :meth:`load`."""
        state = self._require_state()
        if resume:
            if self._resumed_checkpoint or self.ids_leave_process:
                self.run_dir.prepare_resume(state)
            if self.ids_leave_process:
                # Make the skipped id durable before any attempt goes out: a process killed
                # before its own first commit would otherwise leave the old counter on disk,
                # and the next resume would reuse the id this one sent.
                self.run_dir.commit(state.to_checkpoint(), None, ())
        else:
            self.run_dir.create(self.config)
        header = self.run_dir.csv_header()
        if header is not None:
            self._robot_stats = any(c.startswith(ROBOT_STAT_PREFIXES[1]) for c in header)
            self._header = header
        self.pauses.clear_stale()
        self.run_dir.open_log(self.log)
        if self.log.getEffectiveLevel() > logging.INFO:
            self.log.setLevel(logging.INFO)
        self._elapsed_before = state.elapsed_s
        self._started_at = time.monotonic()
        self._last_commit = self._started_at
        best = _best(state.optimizer)
        if best is not None:
            self.run_dir.write_best(*best, self.spec)

    async def close(self) -> None:
        """Let a commit in flight complete (its error, if any, was or is raised by :meth:`run`)."""
        if self._write is not None:
            # A commit in a worker thread cannot be interrupted; let it complete. Its error, if
            # any, was or will be raised by run().
            with contextlib.suppress(Exception):
                await asyncio.shield(self._write)

    def add_progress_listener(self, listener: Callable[[Progress], None]) -> None:
        """Call ``listener(progress)`` on every change of :attr:`progress`."""
        self._listeners.append(listener)

    # -- the run -----------------------------------------------------------------------------

    async def run(self, should_stop: Callable[[], bool] | None = None) -> RunSummary | None:
        """Evolve until the configured number of evaluations, then post-evaluate the best genome.

        Returns when the run is done (at once for a run that was already finished).
        ``should_stop`` is asked between evaluations: once it answers true, the run commits and
        returns None (resume it later). Evaluations that do not count never fail the run; only
        a failure to write the run directory does.
        """
        state = self._require_state()
        try:
            if state.phase == "evolution" and not await self._evolve(should_stop):
                await self._flush()
                return None
            if state.phase == "post-evaluation":
                await self._post_evaluate()
            await self._flush()
        except FileWriteError as exc:
            # Nothing went wrong in the run, and the command line says so in one line: the log
            # gets the line, the console no traceback.
            self.log.error("the run stopped: %s; it can be resumed", exc, extra=FILE_ONLY)
            raise
        except Exception:
            # Into the run's log too: the caller may only see the exception.
            self.log.exception("the run stopped on an error; it can be resumed")
            raise
        opt = state.optimizer
        post = schema.read(self.run_dir.path, PostEvaluation)
        summary = RunSummary(
            run_dir=self.run_dir.path,
            evaluations=opt.evaluations,
            best_fitness=opt.best_fitness,
            best_genome=None if opt.best is None else opt.best.copy(),
            failed_attempts=state.failed_attempts,
            post_evaluation_fitness=None if post is None else post.swarm_fitness,
        )
        self.log.info(
            "run %s done: %d evaluations, best fitness %s, %d failed attempts",
            self.run_id,
            summary.evaluations,
            _fmt(summary.best_fitness),
            summary.failed_attempts,
        )
        self.emit()
        return summary

    async def _evolve(self, should_stop: Callable[[], bool] | None) -> bool:
        """Count evaluations until done (True) or told to stop (False, committed)."""
        state = self._require_state()
        opt = state.optimizer
        experiment = self.experiment
        total = experiment.evolution.evaluations or "endless"
        while not opt.done:
            if should_stop is not None and should_stop():
                await self._commit()
                self.log.info("stopped after %d evaluations", opt.evaluations)
                return False
            if experiment.events:
                await self._arena_events()
            if not self.ids_leave_process and self._commit_due():
                # Before ask: the checkpoint holds no candidate in flight, so a resumed run
                # counts its attempts as the uninterrupted run does.
                await self._commit()
            candidate = opt.ask()
            evaluation_id = self._reserve_attempt()
            if self.ids_leave_process:
                await self._commit()
            await self.evaluator.swarm(state)
            attempt = await self.evaluator.evaluate(
                evaluation_id, candidate.genome, experiment.evaluation_steps, record=False
            )
            if attempt.failure is not None:
                opt.tell_failed()
                await self._attempt_failed(attempt, f"evaluation {opt.evaluations + 1}")
                continue
            # Each in [0, 1]: the codec refuses anything else, so the mean is one too.
            outcome = opt.tell(swarm_fitness(attempt.fitnesses))
            self._rows.append(
                row_cells(
                    outcome.evaluation,
                    outcome.kind,
                    outcome.fitness,
                    outcome.best_fitness,
                    outcome.accepted,
                    state.attempts,
                    attempt.seconds,
                    attempt.safety_share,
                    attempt.robots,
                    attempt.fitnesses,
                    attempt.stats if self._robot_stats else None,
                    swarm=state.swarm_number,
                )
            )
            self._best_changed |= outcome.accepted
            self._counted(outcome.fitness, attempt.safety_share)
            self.log.info(
                "evaluation %d/%s %s: fitness %.4f, best %.4f%s (attempt %d, %.1f s, safety "
                "%.0f %%)%s",
                outcome.evaluation,
                total,
                outcome.kind,
                outcome.fitness,
                outcome.best_fitness,
                ", accepted" if outcome.accepted and outcome.kind == "offspring" else "",
                state.attempts,
                attempt.seconds,
                100 * attempt.safety_share,
                self._status_suffix(),
            )
            state.attempts = 0
            self.emit()
            pause = low_batteries(attempt.robots, attempt.stats, self.config.battery_min_v)
            if pause is not None:
                await self.pause(pause)
        state.phase = "post-evaluation" if experiment.post_evaluation_steps > 0 else "done"
        state.attempts = 0
        await self._commit()
        return True

    async def _post_evaluate(self) -> None:
        state = self._require_state()
        opt = state.optimizer
        assert opt.best is not None, "a post-evaluation needs a counted evaluation"
        steps = self.experiment.post_evaluation_steps
        if self.pause_before_post:
            text = "the evolution is done: place the robots for the post-evaluation"
            await self.pause(Pause("before-post-evaluation", text))
        self.log.info("post-evaluation of the best genome for %d steps", steps)
        while True:
            evaluation_id = self._reserve_attempt()
            if self.ids_leave_process:
                await self._commit()
            await self.evaluator.swarm(state)
            await self.evaluator.before_post_evaluation()
            attempt = await self.evaluator.evaluate(evaluation_id, opt.best, steps, record=True)
            if attempt.failure is None:
                break
            await self._attempt_failed(attempt, "post-evaluation")
        assert attempt.results is not None, "a recorded evaluation returns every robot's result"
        results = {robot: attempt.results[robot] for robot in attempt.robots}
        await self._flush()
        await asyncio.to_thread(
            self.run_dir.write_post_evaluation,
            evaluation_id,
            opt.best_fitness,
            steps,
            results,
            started_at=attempt.started_at,
        )
        await self.evaluator.after_post_evaluation(self.run_dir)
        self.log.info(
            "post-evaluation done: swarm fitness %.4f (%s), safety drove %.0f %% of the steps",
            swarm_fitness(attempt.fitnesses),
            ", ".join(f"{r} {results[r].fitness:.4f}" for r in attempt.robots),
            100 * attempt.safety_share,
        )
        found = dominance(
            attempt.safety_share,
            [r.stats.interventions for r in results.values()],
            at_start=ground_at_start(r.trace.safety for r in results.values() if r.trace),
        )
        if found is not None:
            # A fault of the set-up is a warning; the evolved behaviour itself is a note.
            log = self.log.warning if found.actionable else self.log.info
            log("post-evaluation: %s", found.text)
        state.phase = "done"
        state.attempts = 0
        await self._commit()

    async def pause(self, pause: Pause, over: Callable[[], bool] | None = None) -> None:
        """Wait for a person with the checkpoint on disk (docs/runs.md); ``over()`` ends the
        wait when what it waits for was settled otherwise."""
        await self._commit()
        await self._flush()
        await self.pauses.wait(pause, self.emit, over)
        # The wait is no evaluation's duration: keep it out of the time-left estimate.
        self._last_counted_at = None

    def _reserve_attempt(self) -> int:
        state = self._require_state()
        evaluation_id = state.next_evaluation_id
        state.next_evaluation_id += 1
        state.attempts += 1
        return evaluation_id

    async def _attempt_failed(self, attempt: Evaluation, what: str) -> None:
        """Count and log a failed attempt; pause if the same genome failed repeatedly."""
        state = self._require_state()
        state.failed_attempts += 1
        pause = 0.0
        if state.attempts >= 2:
            pause = min(RETRY_PAUSE * 2 ** (state.attempts - 2), RETRY_PAUSE_MAX)
        if self.evaluator.missing_robots():
            when = " when the swarm is complete"
        else:
            when = f" in {pause:.1f} s" if pause else ""
        self.log.warning(
            "%s, attempt %d (id %d) does not count: %s; the same genome goes out again%s",
            what,
            state.attempts,
            attempt.evaluation_id,
            attempt.failure,
            when,
        )
        self.emit()
        if pause:
            await asyncio.sleep(pause)

    # -- the swarm's changes -------------------------------------------------------------------

    def change_swarm(self, left: str, joined: str | None) -> SwarmChange:
        """Take ``left`` out of the swarm, ``joined`` (a spare) in its place or none; the change.

        Between evaluations, with ``left`` away: the attempt it left failed and goes out again
        to the new swarm, counted once. On disk with the next commit (:meth:`commit_swarm`),
        the CSV's header widened for a robot that joined (:func:`runfiles.schema.widen_header`).
        """
        state = self._require_state()
        change = changed(state.roster or [], left, joined, state.optimizer.evaluations + 1)
        base = self._header or evaluation_header(state.roster or [], robot_stats=self._robot_stats)
        self._header = widen_header(base, change.robots, robot_stats=self._robot_stats)
        self._widen = self._swarm_dirty = True
        state.roster = change.robots
        state.swarms.append(change)
        self.emit()
        return change

    async def commit_swarm(self) -> None:
        """Commit a change of the swarm made since the last commit, if any (from the loop's
        own task, between evaluations)."""
        if self._swarm_dirty:
            await self._commit()
            await self._flush()

    async def robots_gone(self, gone: list[str], away_s: float) -> None:
        """``gone`` have been away for ``away_s`` seconds: go on without them where the
        experiment's ``min_robots`` allows, else pause naming them until a spare takes their
        place (``surprise-master swap``) or a person lets the run wait on (``continue``)."""
        minimum = self.experiment.min_robots
        if minimum is not None and len(self._require_state().roster or []) - len(gone) >= minimum:
            for robot in gone:
                event = dropped_event(self.change_swarm(robot, None), away_s, minimum)
                self.log.warning("%s", event.detail)
                try:
                    append_event(self.run_dir.path, event)  # one line, as the flash's event
                except OSError as exc:
                    self.log.warning("the swarm's change could not be logged: %s", exc)
            await self.commit_swarm()
            return

        def settled() -> bool:  # each swapped out (the swap's desk works meanwhile), or back
            return not set(gone) & set(self.evaluator.missing_robots())

        pause = Pause("robot-gone", gone_text(gone, away_s, self.run_dir.path), tuple(gone))
        await self.pause(pause, settled)
        await self.commit_swarm()

    async def _arena_events(self) -> None:
        """Make the experiment's events due now happen, between evaluations: each once, in
        the checkpoint before its line goes into events.jsonl (docs/changing-arenas.md)."""
        state = self._require_state()
        events, done = self.experiment.events, state.optimizer.evaluations
        for index in due_events(events, state.events_applied, done, self.elapsed_s):
            event = events[index]
            change = await self.evaluator.change_arena(event, index)
            if change is None:  # real robots: a person makes it
                await self.pause(
                    Pause("arena-change", person_text(event, index, self.run_dir.path))
                )
                change = ArenaChange(describe(event))
            for robot in change.left:
                self.change_swarm(robot, None)
            if change.joined:
                roster = [*(state.roster or []), *change.joined]
                base = self._header or evaluation_header(
                    state.roster or [], robot_stats=self._robot_stats
                )
                self._header = widen_header(base, roster, robot_stats=self._robot_stats)
                state.roster = roster
                self._widen = True
            state.events_applied.append(index)
            await self._commit()
            await self._flush()
            line = arena_event(index, change.detail, done, self.elapsed_s)
            self.log.info("after evaluation %d: %s (event %d)", done, change.detail, index)
            try:
                append_event(self.run_dir.path, line)
            except OSError as exc:
                self.log.warning("the arena's change could not be logged: %s", exc)

    # -- commits -----------------------------------------------------------------------------

    def _commit_due(self) -> bool:
        return time.monotonic() - self._last_commit >= self.commit_interval

    async def _commit(self) -> None:
        """Start writing the rows counted since the last commit and the checkpoint of the
        current state.

        Waits for the previous commit first (raising its error), snapshots the state now, and
        returns while a worker thread writes; :meth:`_flush` waits for it.
        """
        await self._flush()
        state = self._require_state()
        rows, self._rows = self._rows, []
        best_changed, self._best_changed = self._best_changed, False
        state.csv_rows += len(rows)
        state.elapsed_s = self.elapsed_s
        # Between evaluations every robot is idle: a simulator's state is consistent now.
        simulation = self.evaluator.snapshot()
        if simulation is not None:
            state.simulation = simulation
        data = state.to_checkpoint()
        if self._header is None and state.roster is not None:
            self._header = evaluation_header(state.roster, robot_stats=self._robot_stats)
        header = list(self._header or [])
        widen, self._widen, self._swarm_dirty = self._widen, False, False
        best = _best(state.optimizer) if best_changed else None
        text = "".join(render_row(cells, header) for cells in rows) or None
        self._last_commit = time.monotonic()

        def write() -> None:
            if widen:  # before the rows it heads
                self.run_dir.rewrite_header(header)
            self.run_dir.commit(data, text, header)
            if best is not None:
                self.run_dir.write_best(*best, self.spec)

        # The thread keeps the event loop free (pings, the next Evaluate) while the disk syncs.
        self._write = asyncio.ensure_future(asyncio.to_thread(write))

    async def _flush(self) -> None:
        """Wait until the latest commit is on disk; raise its error if it failed."""
        if self._write is not None:
            # Shielded: cancelling the run must not abandon a half-done commit.
            await asyncio.shield(self._write)

    # -- progress ----------------------------------------------------------------------------

    @property
    def elapsed_s(self) -> float:
        """Wall-clock seconds this run has been served, over all its resumptions."""
        if not self._started_at:
            return self._elapsed_before
        return self._elapsed_before + time.monotonic() - self._started_at

    @property
    def progress(self) -> Progress:
        """A snapshot of where the run stands."""
        state = self._require_state()
        opt = state.optimizer
        return Progress(
            run_id=self.run_id,
            phase=state.phase,
            waiting=self.evaluator.waiting,
            evaluations=opt.evaluations,
            total=self.experiment.evolution.evaluations,
            best_fitness=opt.best_fitness,
            last_fitness=self._last_fitness,
            robots_connected=self.evaluator.robots_connected,
            robots_expected=self.evaluator.robots_expected,
            failed_attempts=state.failed_attempts,
            elapsed_s=self.elapsed_s,
            time_left_s=self.time_left(),
            safety_share=self._last_safety_share,
            paused=None if self.pauses.current is None else self.pauses.current.text,
        )

    def time_left(self) -> float | None:
        """Estimated seconds until the run is done."""
        state = self._require_state()
        if state.phase == "done":
            return 0.0
        steps = self.experiment.evaluation_steps
        total = self.experiment.evolution.evaluations
        if total is None:  # an endless run: until the person stops it
            return None
        remaining = total - state.optimizer.evaluations
        # Measured once possible, so a simulated swarm in lockstep (far faster than 10 Hz) is
        # estimated right too, its post-evaluation included.
        if self._intervals:
            per_step = statistics.fmean(self._intervals) / steps
        else:
            per_step = self.experiment.step_period
        return (remaining * steps + self.experiment.post_evaluation_steps) * per_step

    def emit(self) -> None:
        """Tell ``on_change`` and every progress listener that something changed."""
        if self._on_change is not None:
            self._on_change()
        if not self._listeners or self.state is None:
            return
        progress = self.progress
        for listener in self._listeners:
            try:
                listener(progress)
            except Exception:
                # A broken display must not stop the run.
                self.log.exception("progress listener %r failed", listener)

    def _counted(self, fitness: float, share: float) -> None:
        now = time.monotonic()
        if self._last_counted_at is not None:
            self._intervals.append(now - self._last_counted_at)
        self._last_counted_at = now
        self._last_fitness = fitness
        self._last_safety_share = share

    def _status_suffix(self) -> str:
        left = self.time_left()
        suffix = f" | robots {self.evaluator.robots_connected}/{self.evaluator.robots_expected}"
        if left is not None:
            suffix += f" | {format_duration(left)} left"
        return suffix

    def _require_state(self) -> RunState:
        if self.state is None:
            raise RuntimeError("the run is not loaded")
        return self.state


def _best(opt: OnePlusOne) -> tuple[np.ndarray, float, int] | None:
    """A copy of the best genome with its fitness and evaluation, if there is one."""
    if opt.best is None or opt.best_fitness is None or opt.best_evaluation is None:
        return None
    return opt.best.copy(), opt.best_fitness, opt.best_evaluation


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"
