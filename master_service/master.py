"""The master: (1+1) online evolution over a swarm of robots, with checkpoint and resume.

One round: wait until the swarm is complete -> send the genome with a fresh evaluation id ->
collect one fitness per robot within the deadline -> if all arrived, tell the algorithm their mean
and log the row; otherwise the round does not count and the same genome goes out again once the
swarm is complete. A robot that drops out pauses the run; it never fails
it. After the last counted evaluation, the best genome is post-evaluated with ``record=True`` and
every robot's trace is stored.

Commit order, which makes resume exactly-once: right after an attempt ends (and before waiting for
robots, so a finished evaluation is never left unsaved), the next attempt's evaluation id is
reserved and one commit writes the finished evaluation's CSV row and the checkpoint (optimizer
state with its pending candidate, the id counter past the reserved id). The commit runs in a worker
thread while the next Evaluate goes out, so the disk's fsync latency is not part of a round's
overhead; a commit starts only when the previous one is on disk. A crash therefore loses at most
the latest commit: its evaluation is done again from the previous checkpoint (whose rows the CSV is
cut back to), and at most one id past the checkpointed counter can have been sent, so a resumed
master starts one id further (1 when there is no checkpoint yet) and commits that counter before
it sends anything; it never reuses an id, however often it is killed.

Use in-process (the ``sim`` command starts agents in the same event loop)::

    async with Master(config, run_dir, secret=secret) as master:
        port = master.port            # bound port; config.port 0 picks a free one
        ...start robots connecting to master.host, port...
        summary = await master.run()  # returns after the post-evaluation
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import os
import statistics
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from master_service.config import MasterConfig, build_ssl_context
from master_service.rounds import Attempt, RoundRunner
from master_service.rundir import (
    EVALUATION_COLUMNS,
    FILE_ONLY,
    POST_EVALUATION,
    Phase,
    RunDir,
    RunState,
    format_row,
)
from master_service.server import RobotServer, Session
from minimize_surprise.errors import ConfigError, FileWriteError
from minimize_surprise.evolution import OnePlusOne
from minimize_surprise.fitness import swarm_fitness
from minimize_surprise.network import GenomeLayout, spec_from_config
from minimize_surprise.safety import dominance_warning
from minimize_surprise.session import TAG_SIZE
from minimize_surprise.wire import REFUSED_UNKNOWN_ROBOT, Evaluate, Failed, Result, encode_payload
from telemetry.config import require_client_library
from telemetry.payloads import RunStatus, master_status_suffix, now, run_status_suffix
from telemetry.publisher import TelemetryPublisher

__all__ = ["Master", "Progress", "RunSummary"]

#: How often live.json is refreshed at the least; ``status`` calls a master silent for 5 periods
#: gone.
LIVE_INTERVAL: Final = 2.0
#: Shortest time between two live.json writes: a thousand robots joining at once cost a few
#: writes, not a thousand.
LIVE_MIN_INTERVAL: Final = 0.2
#: Pause before the third and later attempt of the same genome, doubling up to the cap. A robot
#: that fails at once (a broken sensor answers Failed immediately) would otherwise be retried in a
#: tight loop that fills the log while the lab looks for the fault.
RETRY_PAUSE: Final = 0.5
RETRY_PAUSE_MAX: Final = 10.0
#: Counted evaluations the time-left estimate averages over: recent enough to follow a robot that
#: became slow, long enough to smooth one retried round.
ETA_WINDOW: Final = 20


@dataclass(frozen=True)
class Progress:
    """Where a running master stands; handed to progress listeners on every change.

    ``phase`` is the checkpoint's phase; ``waiting`` is true while the swarm is incomplete.
    ``time_left_s`` is an estimate (None when unknown).
    """

    run_id: str
    phase: Phase
    waiting: bool
    evaluations: int
    total: int
    best_fitness: float | None
    last_fitness: float | None
    robots_connected: int
    robots_expected: int
    failed_attempts: int
    elapsed_s: float
    time_left_s: float | None
    #: share of the last counted evaluation's steps in which the safety layer drove
    safety_share: float | None = None


@dataclass(frozen=True)
class RunSummary:
    """What :meth:`Master.run` returns."""

    run_dir: Path
    evaluations: int
    best_fitness: float | None
    best_genome: np.ndarray | None
    failed_attempts: int
    post_evaluation_fitness: float | None


class Master:
    """The laptop service for one run (new, or resumed with ``resume=True``).

    ``secret`` is the shared secret's bytes (see :func:`master_service.config.load_secret`).
    ``on_progress`` (also :meth:`add_progress_listener`) is called with a :class:`Progress` on
    every change. ``before_post_evaluation`` is awaited before each attempt of the
    post-evaluation, while every robot is idle; ``snapshot`` (a simulator's) returns its state at
    every commit, kept in the checkpoint. Construction validates and touches no file;
    :meth:`start` (or ``async with``) binds the port and creates or opens the run directory;
    :meth:`run` evolves and post-evaluates; :meth:`close` says Bye to the robots and closes
    everything.
    """

    def __init__(
        self,
        config: MasterConfig,
        run_dir: str | Path,
        *,
        secret: bytes,
        resume: bool = False,
        on_progress: Callable[[Progress], None] | None = None,
        before_post_evaluation: Callable[[], Awaitable[None]] | None = None,
        snapshot: Callable[[], dict[str, Any]] | None = None,
    ) -> None:
        if config.experiment is None:
            raise ConfigError(
                "the experiment is not loaded: use load_master_config()", key="experiment_file"
            )
        if not secret:
            raise ConfigError("the shared secret is empty", key="secret_file")
        self.config = config
        self.experiment = config.experiment
        self.spec = spec_from_config(self.experiment)
        self.genome_size = GenomeLayout(self.spec).size
        # The largest Evaluate this run can send (ids and step counts at their widest).
        widest = 2**64 - 1
        probe = Evaluate(
            evaluation_id=widest,
            genome=bytes(8 * self.genome_size),
            spec=self.spec,
            steps=widest,
            step_period=self.experiment.step_period,
            record=False,  # one byte either way; a recorded one may not have this many steps
        )
        if len(encode_payload(probe)) + TAG_SIZE > config.max_frame_size:
            raise ConfigError(
                f"{config.max_frame_size} bytes cannot hold the genome of "
                f"{self.genome_size} values sent with every evaluation",
                key="max_frame_size",
            )
        self.run_dir = RunDir(run_dir)
        self.run_id = self.run_dir.path.resolve().name
        self.resume = resume
        self._before_post_evaluation = before_post_evaluation
        self._snapshot = snapshot
        self._ssl = build_ssl_context(config.tls) if config.tls is not None else None
        self._listeners: list[Callable[[Progress], None]] = []
        if on_progress is not None:
            self._listeners.append(on_progress)
        #: the MQTT publisher of the run's status, when a broker is configured
        self.telemetry: TelemetryPublisher | None = None
        if config.telemetry is not None and config.telemetry.enabled:
            require_client_library(config.telemetry)
            self.telemetry = TelemetryPublisher(
                config.telemetry, status_suffix=master_status_suffix(), name="telemetry[master]"
            )
            self._listeners.append(self._publish_status)
        # One logger per run; the run's log file hangs on it, so two masters in one process
        # (tests, the sim command) keep separate logs and there is no global state.
        self.log = logging.getLogger(f"master_service.run.{self.run_id}")
        self.state: RunState | None = None
        self.server = RobotServer(
            host=config.host,
            port=config.port,
            secret=secret,
            sensors=self.experiment.sensors,
            run_id=self.run_id,
            heartbeat_interval=config.heartbeat_interval,
            handshake_timeout=config.handshake_timeout,
            max_pending_connections=config.max_pending_connections,
            max_frame_size=config.max_frame_size,
            ssl_context=self._ssl,
            admit=self._admit,
            on_join=self._on_join,
            on_leave=self._on_leave,
            on_message=self._on_message,
            logger=self.log,
        )
        self.rounds = RoundRunner(self.server, config.round_margin, self.log)
        self._swarm_changed = asyncio.Event()
        self._live_changed = asyncio.Event()
        self._waiting = False
        self._started_at = 0.0
        self._elapsed_before = 0.0
        self._last_counted_at: float | None = None
        self._intervals: collections.deque[float] = collections.deque(maxlen=ETA_WINDOW)
        self._last_fitness: float | None = None
        self._last_safety_share: float | None = None
        self._write: asyncio.Future[None] | None = None
        self._live_task: asyncio.Task[None] | None = None
        self._live_failed = False
        self._started = False

    # -- lifecycle ---------------------------------------------------------------------------

    async def start(self) -> None:
        """Bind the port, create (or open and repair) the run directory, accept robots."""
        if self._started:
            raise RuntimeError("the master was started already")
        self._started = True
        state = None
        if self.resume:
            self.run_dir.check_experiment(self.experiment)
            state = self.run_dir.read_state(self.config)
            if state is not None:
                # The attempt in flight when the master stopped may have used the checkpointed
                # counter (see the module docstring): skip it.
                state.next_evaluation_id += 1
        else:
            self.run_dir.check_new()
        if state is None:
            experiment = self.experiment
            optimizer = OnePlusOne(experiment.evolution, self.genome_size, experiment.seed)
            state = RunState(run_id=self.run_id, optimizer=optimizer)
            if self.resume:
                # A master stopped before its first commit may have sent id 0.
                state.next_evaluation_id = 1
        await self.server.bind()
        try:
            if self.resume:
                self.run_dir.prepare_resume(state)
                # Make the skipped id durable before any attempt goes out: a master killed
                # before its own first commit would otherwise leave the old counter on disk,
                # and the next resume would reuse the id this one sent.
                self.run_dir.commit(state.to_json(), None, ())
            else:
                self.run_dir.create(self.config)
            self._open_log()
        except BaseException:
            await self.server.close()
            raise
        self.state = state
        self._elapsed_before = state.elapsed_s
        self._started_at = time.monotonic()
        self._write_best()
        await self.server.start_serving()
        # live.json announces the port: only once the socket accepts connections.
        self._write_live()
        self._live_task = asyncio.create_task(self._refresh_live(), name="live.json")
        optimizer = state.optimizer
        self.log.info(
            "%s run %s: listening on %s:%d%s; %d/%d evaluations done, swarm of %d robots",
            "resumed" if self.resume else "started",
            self.run_id,
            self.host,
            self.port,
            " (TLS)" if self._ssl else "",
            optimizer.evaluations,
            self.experiment.evolution.evaluations,
            self.config.robot_count,
        )
        if self.telemetry is not None:
            self.telemetry.start()  # connects in the background; returns at once
        self._emit()

    async def close(self) -> None:
        """Finish pending writes, say Bye to the robots, close the connections and the log."""
        if self._live_task is not None:
            self._live_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._live_task
            self._live_task = None
        await self.server.close()
        if self._write is not None:
            # A commit in a worker thread cannot be interrupted; let it complete. Its error, if
            # any, was or will be raised by run().
            with contextlib.suppress(Exception):
                await asyncio.shield(self._write)
        self.run_dir.close()
        if self.state is not None:
            with contextlib.suppress(OSError):
                self.run_dir.write_live(self._live_data(running=False))
        self.run_dir.close_log(self.log)
        if self.telemetry is not None:
            if self.state is not None:
                self._publish_status(self.progress, online=False)
            await self.telemetry.aclose()  # bounded by telemetry.publisher.CLOSE_TIMEOUT

    async def __aenter__(self) -> Master:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.close()

    @property
    def host(self) -> str:
        """The configured listening host."""
        return self.config.host

    @property
    def port(self) -> int:
        """The bound port (after :meth:`start`)."""
        return self.server.port

    @property
    def connected_robots(self) -> list[str]:
        """Ids of the robots connected now, sorted."""
        return sorted(self.server.sessions)

    @property
    def overheads(self) -> list[float]:
        """Seconds from a round's last Result in to the next round's Evaluate out, per round."""
        return list(self.rounds.overheads)

    def add_progress_listener(self, listener: Callable[[Progress], None]) -> None:
        """Call ``listener(progress)`` on every change of :attr:`progress`."""
        self._listeners.append(listener)

    # -- the run -----------------------------------------------------------------------------

    async def run(self) -> RunSummary:
        """Evolve until the configured number of evaluations, then post-evaluate the best genome.

        Returns when the run is done (at once for a run that was already finished). Robots
        dropping out never fail the run; only a failure to write the run directory does.
        """
        state = self._require_state()
        try:
            if state.phase == "evolution":
                await self._evolve()
            if state.phase == "post-evaluation":
                await self._post_evaluate()
            await self._flush()
        except FileWriteError as exc:
            # Nothing went wrong in the master, and the command line says so in one line: the
            # log gets the line, the console no traceback.
            self.log.error("the run stopped: %s; it can be resumed", exc, extra=FILE_ONLY)
            raise
        except Exception:
            # Into the run's log too: the caller may only see the exception.
            self.log.exception("the run stopped on an error; it can be resumed")
            raise
        opt = state.optimizer
        post = self.run_dir.read_json(POST_EVALUATION)
        summary = RunSummary(
            run_dir=self.run_dir.path,
            evaluations=opt.evaluations,
            best_fitness=opt.best_fitness,
            best_genome=None if opt.best is None else opt.best.copy(),
            failed_attempts=state.failed_attempts,
            post_evaluation_fitness=None if post is None else post.get("swarm_fitness"),
        )
        self.log.info(
            "run %s done: %d evaluations, best fitness %s, %d failed attempts",
            self.run_id,
            summary.evaluations,
            _fmt(summary.best_fitness),
            summary.failed_attempts,
        )
        self._emit()
        return summary

    async def _evolve(self) -> None:
        state = self._require_state()
        opt = state.optimizer
        total = self.experiment.evolution.evaluations
        row: str | None = None
        accepted = False
        while not opt.done:
            candidate = opt.ask()
            evaluation_id = self._reserve_attempt()
            await self._commit(row, best_changed=accepted)
            row, accepted = None, False
            robots = await self._wait_for_swarm()
            attempt = await self.rounds.run(
                evaluation_id=evaluation_id,
                genome=candidate.genome,
                spec=self.spec,
                steps=self.experiment.evaluation_steps,
                step_period=self.experiment.step_period,
                record=False,
                robots=robots,
            )
            if not attempt.ok:
                opt.tell_failed()
                await self._attempt_failed(attempt, f"evaluation {opt.evaluations + 1}")
                continue
            fitnesses = attempt.fitnesses()
            # Each in [0, 1]: the codec refuses anything else, so the mean is one too.
            fitness = swarm_fitness(fitnesses)
            outcome = opt.tell(fitness)
            duration = attempt.completed - attempt.started
            share = attempt.safety_share()
            row = format_row(
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
            accepted = outcome.accepted
            self._counted(outcome.fitness, share)
            self.log.info(
                "evaluation %d/%d %s: fitness %.4f, best %.4f%s (attempt %d, %.1f s, safety "
                "%.0f %%)%s",
                outcome.evaluation,
                total,
                outcome.kind,
                outcome.fitness,
                outcome.best_fitness,
                ", accepted" if outcome.accepted and outcome.kind == "offspring" else "",
                state.attempts,
                duration,
                100 * share,
                self._status_suffix(),
            )
            state.attempts = 0
            self._emit()
        if self.experiment.post_evaluation_steps > 0:
            state.phase = "post-evaluation"
        else:
            state.phase = "done"
        state.attempts = 0
        await self._commit(row, best_changed=accepted)

    async def _post_evaluate(self) -> None:
        state = self._require_state()
        opt = state.optimizer
        assert opt.best is not None, "a post-evaluation needs a counted evaluation"
        steps = self.experiment.post_evaluation_steps
        self.log.info("post-evaluation of the best genome for %d steps", steps)
        while True:
            evaluation_id = self._reserve_attempt()
            await self._commit(None)
            robots = await self._wait_for_swarm()
            if self._before_post_evaluation is not None:
                # The simulator resets its arena here, as the paper does before this run.
                await self._before_post_evaluation()
            attempt = await self.rounds.run(
                evaluation_id=evaluation_id,
                genome=opt.best,
                spec=self.spec,
                steps=steps,
                step_period=self.experiment.step_period,
                record=True,
                robots=robots,
            )
            if attempt.ok:
                break
            await self._attempt_failed(attempt, "post-evaluation")
        results = {robot: attempt.results[robot] for robot in attempt.robots}
        await self._flush()
        await asyncio.to_thread(
            self.run_dir.write_post_evaluation, evaluation_id, opt.best_fitness, steps, results
        )
        share = attempt.safety_share()
        self.log.info(
            "post-evaluation done: swarm fitness %.4f (%s), safety drove %.0f %% of the steps",
            swarm_fitness(attempt.fitnesses()),
            ", ".join(f"{r} {attempt.results[r].fitness:.4f}" for r in attempt.robots),
            100 * share,
        )
        warning = dominance_warning(share, [r.stats.interventions for r in results.values()])
        if warning is not None:
            self.log.warning("post-evaluation: %s", warning)
        state.phase = "done"
        state.attempts = 0
        await self._commit(None)

    def _reserve_attempt(self) -> int:
        state = self._require_state()
        evaluation_id = state.next_evaluation_id
        state.next_evaluation_id += 1
        state.attempts += 1
        return evaluation_id

    async def _attempt_failed(self, attempt: Attempt, what: str) -> None:
        """Count and log a failed attempt; pause if the same genome failed repeatedly."""
        state = self._require_state()
        state.failed_attempts += 1
        pause = 0.0
        if state.attempts >= 2:
            pause = min(RETRY_PAUSE * 2 ** (state.attempts - 2), RETRY_PAUSE_MAX)
        if self.missing_robots():
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
        self._emit()
        if pause:
            await asyncio.sleep(pause)

    async def _commit(self, row: str | None, *, best_changed: bool = False) -> None:
        """Start writing ``row`` (if any) and the checkpoint of the current state.

        Waits for the previous commit first (raising its error), snapshots the state now, and
        returns while a worker thread writes; :meth:`_flush` waits for it.
        """
        await self._flush()
        state = self._require_state()
        if row is not None:
            state.csv_rows += 1
        state.elapsed_s = self.elapsed_s
        if self._snapshot is not None:
            # Between rounds every robot is idle: a simulator's state is consistent now.
            state.simulation = self._snapshot()
        data = state.to_json()
        roster = state.roster or []
        header = [*EVALUATION_COLUMNS, *(f"fitness_{robot}" for robot in roster)]
        opt = state.optimizer
        best = None
        if best_changed and opt.best is not None:
            best = (opt.best.copy(), opt.best_fitness, opt.best_evaluation)

        def write() -> None:
            self.run_dir.commit(data, row, header)
            if best is not None:
                self.run_dir.write_best(best[0], best[1], best[2], self.spec)

        # The thread keeps the event loop free (pings, the next Evaluate) while the disk syncs.
        self._write = asyncio.ensure_future(asyncio.to_thread(write))

    async def _flush(self) -> None:
        """Wait until the latest commit is on disk; raise its error if it failed."""
        if self._write is not None:
            # Shielded: cancelling the run must not abandon a half-done commit.
            await asyncio.shield(self._write)

    # -- the swarm ---------------------------------------------------------------------------

    def missing_robots(self) -> list[str]:
        """The swarm's robots not connected now (empty before the swarm is fixed)."""
        roster = self._require_state().roster
        if roster is None:
            return []
        return [robot for robot in roster if robot not in self.server.sessions]

    async def _wait_for_swarm(self) -> list[str]:
        """Wait until every robot of the swarm is connected; fix the swarm the first time."""
        state = self._require_state()
        logged = False
        while True:
            if state.roster is None and len(self.server.sessions) >= self.config.robot_count:
                state.roster = sorted(self.server.sessions)[: self.config.robot_count]
                self.log.info("the swarm is %s", ", ".join(state.roster))
            if state.roster is not None and not self.missing_robots():
                if self._waiting:
                    self._waiting = False
                    self._emit()
                return state.roster
            if not logged:
                self._waiting = True
                self.log.info("waiting for robots: %s", self._robots_text())
                self._emit()
                logged = True
            self._swarm_changed.clear()
            await self._swarm_changed.wait()

    def _admit(self, robot_id: str) -> tuple[str, str] | None:
        allowed = self.config.allowed_robots
        if allowed and robot_id not in allowed:
            return REFUSED_UNKNOWN_ROBOT, f"{robot_id} is not among the allowed robots"
        roster = self.state.roster if self.state is not None else None
        if roster is not None:
            if robot_id not in roster:
                return REFUSED_UNKNOWN_ROBOT, f"{robot_id} is not in this run's swarm"
        elif (
            robot_id not in self.server.sessions
            and len(self.server.sessions) >= self.config.robot_count
        ):
            return REFUSED_UNKNOWN_ROBOT, f"the swarm of {self.config.robot_count} is complete"
        return None

    def _on_join(self, session: Session) -> None:
        self._swarm_changed.set()
        self._emit()

    def _on_leave(self, session: Session, reason: str) -> None:
        self.rounds.on_leave(session, reason)
        self._swarm_changed.set()
        self._emit()

    def _on_message(self, session: Session, msg: Result | Failed) -> None:
        self.rounds.on_message(session, msg)

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
            waiting=self._waiting,
            evaluations=opt.evaluations,
            total=self.experiment.evolution.evaluations,
            best_fitness=opt.best_fitness,
            last_fitness=self._last_fitness,
            robots_connected=len(self.server.sessions),
            robots_expected=self.config.robot_count,
            failed_attempts=state.failed_attempts,
            elapsed_s=self.elapsed_s,
            time_left_s=self._time_left(),
            safety_share=self._last_safety_share,
        )

    def _time_left(self) -> float | None:
        state = self._require_state()
        if state.phase == "done":
            return 0.0
        steps = self.experiment.evaluation_steps
        remaining = self.experiment.evolution.evaluations - state.optimizer.evaluations
        # Measured once possible, so a simulated swarm in lockstep (far faster than 10 Hz) is
        # estimated right too, its post-evaluation included.
        if self._intervals:
            per_step = statistics.fmean(self._intervals) / steps
        else:
            per_step = self.experiment.step_period
        return (remaining * steps + self.experiment.post_evaluation_steps) * per_step

    def _counted(self, fitness: float, share: float) -> None:
        now = time.monotonic()
        if self._last_counted_at is not None:
            self._intervals.append(now - self._last_counted_at)
        self._last_counted_at = now
        self._last_fitness = fitness
        self._last_safety_share = share

    def _robots_text(self) -> str:
        connected = len(self.server.sessions)
        text = f"{connected}/{self.config.robot_count} connected"
        missing = self.missing_robots()
        if missing:
            text += f", missing {', '.join(missing)}"
        return text

    def _status_suffix(self) -> str:
        left = self._time_left()
        suffix = f" | robots {len(self.server.sessions)}/{self.config.robot_count}"
        if left is not None:
            suffix += f" | {format_duration(left)} left"
        return suffix

    def _publish_status(self, progress: Progress, *, online: bool = True) -> None:
        """Progress listener: the retained ``<prefix>/run/status``. Only queues (latest wins)."""
        if self.telemetry is None:
            return
        status = RunStatus(
            t=now(),
            online=online,
            run_id=progress.run_id,
            phase=progress.phase,
            waiting=progress.waiting,
            evaluations=progress.evaluations,
            total=progress.total,
            best_fitness=progress.best_fitness,
            last_fitness=progress.last_fitness,
            robots_connected=progress.robots_connected,
            robots_expected=progress.robots_expected,
            robots=self.connected_robots,
            failed_attempts=progress.failed_attempts,
            elapsed_s=round(progress.elapsed_s, 3),
            time_left_s=None if progress.time_left_s is None else round(progress.time_left_s, 1),
        )
        self.telemetry.publish_nowait(run_status_suffix(), status, retain=True)

    def _emit(self) -> None:
        self._live_changed.set()
        if not self._listeners or self.state is None:
            return
        progress = self.progress
        for listener in self._listeners:
            try:
                listener(progress)
            except Exception:
                # A broken display must not stop the run.
                self.log.exception("progress listener %r failed", listener)

    # -- files -------------------------------------------------------------------------------

    def _open_log(self) -> None:
        self.run_dir.open_log(self.log)
        if self.log.getEffectiveLevel() > logging.INFO:
            self.log.setLevel(logging.INFO)

    def _write_best(self) -> None:
        opt = self._require_state().optimizer
        if opt.best is not None and opt.best_fitness is not None:
            self.run_dir.write_best(opt.best, opt.best_fitness, opt.best_evaluation, self.spec)

    def _live_data(self, *, running: bool) -> dict[str, Any]:
        state = self._require_state()
        return {
            "pid": os.getpid(),
            "running": running,
            "host": self.host,
            "port": self.port,
            "robots": self.connected_robots,
            "phase": state.phase,
            "waiting": self._waiting,
            "evaluations": state.optimizer.evaluations,
            "time_left_s": self._time_left(),
            "updated_at": time.time(),
        }

    def _write_live(self) -> None:
        self.run_dir.write_live(self._live_data(running=True))

    async def _refresh_live(self) -> None:
        while True:
            # asyncio.timeout, not wait_for: in Python 3.11 wait_for can swallow a cancellation
            # that arrives as the wait completes, and close() would wait for this task forever.
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(LIVE_INTERVAL):
                    await self._live_changed.wait()
            self._live_changed.clear()
            data = self._live_data(running=True)
            try:
                await asyncio.to_thread(self.run_dir.write_live, data)
            except OSError as exc:
                self._live_write_failed(exc)
            else:
                self._live_failed = False
            await asyncio.sleep(LIVE_MIN_INTERVAL)

    def _live_write_failed(self, exc: OSError) -> None:
        # Once per spell, into the log only: the directory or the disk that refuses live.json
        # refuses the next commit too, and that stops the run with one line on the console.
        if not self._live_failed:
            self._live_failed = True
            self.log.warning("%s; live.json is not current", exc, extra=FILE_ONLY)

    def _require_state(self) -> RunState:
        if self.state is None:
            raise RuntimeError("the master is not started")
        return self.state


def format_duration(seconds: float) -> str:
    """``1h02m``, ``5m07s`` or ``42s``."""
    seconds = max(0, round(seconds))
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    if hours:
        return f"{hours}h{minutes:02d}m"
    if minutes:
        return f"{minutes}m{secs:02d}s"
    return f"{secs}s"


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"
