"""The master: (1+1) online evolution over a swarm of robots, with checkpoint and resume.

One round: wait until the swarm is complete -> send the genome with a fresh evaluation id ->
collect one fitness per robot within the deadline -> if all arrived, tell the algorithm their mean
and log the row; otherwise the round does not count and the same genome goes out again once the
swarm is complete. A robot that drops out pauses the run; it never fails it; one gone for good
is swapped or let go (:mod:`master_service.swap`). After the last counted evaluation, the best
genome is post-evaluated with ``record=True`` and every robot's trace is stored.

Why one file of over 600 lines: :class:`Master` is one object, the robots' side of one run; what
could stand alone already does (the loop, the rounds, the escape, swap and stop desks, the run
directory).

The loop itself, with its commits, resume and progress, is
:class:`~master_service.evolution_run.EvolutionRun`, shared with the compiled engine; the master is
its :class:`~master_service.evolution_run.Evaluator` for robots over TCP.

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
import contextlib
import logging
import os
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any, Final

import numpy as np

from master_service.config import MasterConfig, build_ssl_context, inventory_of
from master_service.escape import EscapeDesk
from master_service.evaluation import ArenaChange, Evaluation, Progress, RunSummary
from master_service.evolution_run import EvolutionRun
from master_service.mark import MarkDesk
from master_service.pause import Pause
from master_service.progress import run_status
from master_service.replay import ReplaySource, write_replay_file
from master_service.rounds import RoundRunner
from master_service.rundir import FILE_ONLY, RunDir, RunState
from master_service.server import Answer, RobotServer, Session
from master_service.stopall import STOP_PAUSE_TEXT, StopDesk
from master_service.swap import SwapDesk
from master_service.swarm import AwayClock, changes_text
from minimize_surprise import __version__
from minimize_surprise.errors import ConfigError
from minimize_surprise.events import ArenaEvent, RobotsJoin
from minimize_surprise.network import GenomeLayout, spec_from_config
from minimize_surprise.provenance import software_commit
from minimize_surprise.session import TAG_SIZE
from minimize_surprise.wire import (
    REFUSED_UNKNOWN_ROBOT,
    CheckReport,
    EscapeReply,
    Evaluate,
    Stopped,
    encode_payload,
)
from runfiles.schema import (
    EVENT_POST_EVALUATION,
    LIVE_INTERVAL,
    Event,
    Live,
    Software,
    append_event,
)
from telemetry.config import require_client_library
from telemetry.payloads import master_status_suffix, run_status_suffix
from telemetry.publisher import TelemetryPublisher

__all__ = ["Master", "Progress", "RunSummary"]

#: Shortest time between two live.json writes: a thousand robots joining at once cost a few
#: writes, not a thousand.
LIVE_MIN_INTERVAL: Final = 0.2


class Master:
    """The laptop service for one run (new, or resumed with ``resume=True``).

    ``secret`` is the shared secret's bytes (see :func:`master_service.config.load_secret`).
    ``on_progress`` (also :meth:`add_progress_listener`) is called with a :class:`Progress` on
    every change. ``before_post_evaluation`` is awaited before each attempt of the
    post-evaluation, while every robot is idle; ``snapshot`` (a simulator's) returns its state at
    every commit, kept in the checkpoint. ``replay`` post-evaluates that genome instead of
    evolving one (:mod:`master_service.replay`). Construction validates and touches no file;
    :meth:`start` (or ``async with``) binds the port and creates or opens the run directory;
    :meth:`run` evolves and post-evaluates; :meth:`close` says Bye to the robots and closes
    everything.
    """

    #: Robots report their overruns, read failures and battery (columns of evaluations.csv).
    reports_robot_stats = True

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
        replay: ReplaySource | None = None,
        change_arena: Callable[[ArenaEvent, int], Awaitable[ArenaChange]] | None = None,
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
        self.replay = replay
        self._before_post_evaluation = before_post_evaluation
        self._snapshot = snapshot
        self._change_arena = change_arena
        for index, event in enumerate(self.experiment.events):
            if change_arena is None and isinstance(event, RobotsJoin):
                raise ConfigError(
                    "robots join only in simulation; on real robots a spare joins through "
                    "`surprise-master swap`",
                    key=f"events[{index}].kind",
                )
        self._ssl = build_ssl_context(config.tls) if config.tls is not None else None
        # One logger per run; the run's log file hangs on it, so two masters in one process
        # (tests, the sim command) keep separate logs and there is no global state.
        self.log = logging.getLogger(f"master_service.run.{self.run_id}")
        self._live_changed = asyncio.Event()
        #: each robot's battery, overruns and read failures in its last counted evaluation
        self._robot_state: dict[str, dict[str, Any]] = {}
        #: the run's evolution loop, with this master as its evaluator
        self.evolution = EvolutionRun(
            config,
            self.run_dir,
            self.spec,
            self,
            self.log,
            ids_leave_process=True,
            on_change=self._live_changed.set,
        )
        if on_progress is not None:
            self.evolution.add_progress_listener(on_progress)
        #: the MQTT publisher of the run's status, when a broker is configured
        self.telemetry: TelemetryPublisher | None = None
        if config.telemetry is not None and config.telemetry.enabled:
            require_client_library(config.telemetry)
            self.telemetry = TelemetryPublisher(
                config.telemetry, status_suffix=master_status_suffix(), name="telemetry[master]"
            )
            self.evolution.add_progress_listener(self._publish_status)
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
        #: the experimenter's escapes (``surprise-master escape``), asked through the run dir
        self.escapes = EscapeDesk(
            self.run_dir,
            self.server,
            self.log,
            members=self._members,
            paused=self._paused,
            evaluating=self._evaluating,
        )
        self._escape_task: asyncio.Task[None] | None = None
        # The inventory's spares stand by once the swarm is fixed, never in it from the start.
        self._spares = [] if (inventory := inventory_of(config)) is None else inventory.spares
        allowed = [*config.allowed_robots, *self._spares] if config.allowed_robots else []
        #: spares brought in for robots gone for good (``surprise-master swap``)
        self.swaps = SwapDesk(
            self.run_dir, self.server, self.log, lambda: self.state, allowed, self._swap
        )
        self._swap_task: asyncio.Task[None] | None = None
        #: every robot stopped (``surprise-master fleet stop --run``): the run pauses
        self.stops = StopDesk(
            self.run_dir, self.server, self.log, members=self._members, on_stop=self._fleet_stop
        )
        self._stop_task: asyncio.Task[None] | None = None
        #: a person's marks (``surprise-master mark``)
        self.marks = MarkDesk(self.run_dir, self.log, lambda: self.state, lambda: self.elapsed_s)
        self._mark_task: asyncio.Task[None] | None = None
        #: the pause a fleet stop asked for, taken by the next swarm()
        self._stop_pause: Pause | None = None
        #: since when each robot of the swarm has been away (gone for good: robot_gone_after)
        self.away = AwayClock(config.robot_gone_after)
        self._swarm_changed = asyncio.Event()
        self._waiting = False
        self._live_task: asyncio.Task[None] | None = None
        self._live_failed = False
        self._started = False

    # -- lifecycle ---------------------------------------------------------------------------

    async def start(self) -> None:
        """Bind the port, create (or open and repair) the run directory, accept robots."""
        if self._started:
            raise RuntimeError("the master was started already")
        self._started = True
        self.evolution.load(resume=self.resume, replay=self.replay)
        await self.server.bind()
        try:
            self.evolution.open(resume=self.resume)
            if self.replay is not None and not self.resume:
                write_replay_file(self.run_dir, self.replay)
            self.run_dir.record_master_software(
                Software(version=__version__, commit=software_commit())
            )
        except BaseException:
            await self.server.close()
            raise
        await self.server.start_serving()
        # live.json announces the port: only once the socket accepts connections.
        self._write_live()
        self._live_task = asyncio.create_task(self._refresh_live(), name="live.json")
        self._escape_task = asyncio.create_task(self.escapes.run(), name="escapes")
        self._swap_task = asyncio.create_task(self.swaps.run(), name="swaps")
        self._stop_task = asyncio.create_task(self.stops.run(), name="fleet-stops")
        self._mark_task = asyncio.create_task(self.marks.run(), name="marks")
        self.away.start(self._require_state().roster or [])  # a resumed swarm's: not back yet
        optimizer = self._require_state().optimizer
        self.log.info(
            "%s run %s: listening on %s:%d%s; %d/%s evaluations done, swarm of %d robots%s",
            "resumed" if self.resume else "started",
            self.run_id,
            self.host,
            self.port,
            " (TLS)" if self._ssl else "",
            optimizer.evaluations,
            self.experiment.evolution.evaluations,
            self.robots_expected,
            changes_text(self._require_state().swarms),
        )
        if self.telemetry is not None:
            self.telemetry.start()  # connects in the background; returns at once
        self.evolution.emit()

    async def close(self) -> None:
        """Finish pending writes, say Bye to the robots, close the connections and the log."""
        tasks = (self._live_task, self._escape_task, self._swap_task, self._stop_task)
        for task in (*tasks, self._mark_task):
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        self._live_task = self._escape_task = self._swap_task = self._stop_task = None
        self._mark_task = None
        await self.server.close()
        await self.evolution.close()
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
    def state(self) -> RunState | None:
        """The run's state (None before :meth:`start`)."""
        return self.evolution.state

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
        self.evolution.add_progress_listener(listener)

    async def run(self) -> RunSummary:
        """Evolve until the configured number of evaluations, then post-evaluate the best genome.

        Returns when the run is done (at once for a run that was already finished). Robots
        dropping out never fail the run; only a failure to write the run directory does.
        """
        self._require_state()
        summary = await self.evolution.run()
        assert summary is not None, "a master's run is stopped by cancelling it"
        return summary

    # -- the evaluator: rounds over the robots (master_service.evolution_run.Evaluator) ------

    @property
    def robots_connected(self) -> int:
        """Robots of the swarm connected now (before it is fixed: every robot connected)."""
        roster = self.state.roster if self.state is not None else None
        if roster is None:
            return len(self.server.sessions)
        return sum(robot in self.server.sessions for robot in roster)

    @property
    def robots_expected(self) -> int:
        """Robots the swarm has (fewer than configured once robots went for good)."""
        roster = self.state.roster if self.state is not None else None
        return self.config.robot_count if roster is None else len(roster)

    @property
    def waiting(self) -> bool:
        """True while the run waits for robots."""
        return self._waiting

    def missing_robots(self) -> list[str]:
        """The swarm's robots not connected now (empty before the swarm is fixed)."""
        roster = self._require_state().roster
        if roster is None:
            return []
        return [robot for robot in roster if robot not in self.server.sessions]

    async def swarm(self, state: RunState) -> list[str]:
        """Wait until every robot of the swarm is connected; fix the swarm the first time. One
        away for ``robot_gone_after`` is gone for good (:meth:`EvolutionRun.robots_gone`)."""
        logged = False
        while True:
            if self._stop_pause is not None:
                await self.evolution.pause(self._stop_pause)
                self._stop_pause = None
            if state.roster is None and len(self.server.sessions) >= self.config.robot_count:
                state.roster = sorted(self.server.sessions)[: self.config.robot_count]
                self.log.info("the swarm is %s", ", ".join(state.roster))
            await self.evolution.commit_swarm()
            if state.roster is not None and not self.missing_robots():
                if self._waiting:
                    self._waiting = False
                    self.evolution.emit()
                return state.roster
            gone, away, wake_in = self.away.gone(self.missing_robots())
            if gone:
                await self.evolution.robots_gone(gone, away)
                # A person who let the run wait on gives the robots another spell.
                self.away.restart(self.missing_robots())
                logged = False
                continue
            if not logged:
                self._waiting = True
                self.log.info("waiting for robots: %s", self._robots_text())
                self.evolution.emit()
                logged = True
            self._swarm_changed.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(wake_in):
                    await self._swarm_changed.wait()

    def _swap(self, gone: str, spare: str) -> int:
        """The swap desk's change: ``spare`` in ``gone``'s place from the evaluation returned."""
        change = self.evolution.change_swarm(gone, spare)
        self.away.back(gone)
        self._swarm_changed.set()
        return change.from_evaluation

    async def evaluate(
        self, evaluation_id: int, genome: np.ndarray, steps: int, *, record: bool
    ) -> Evaluation:
        """One round: ``genome`` out to every robot of the swarm, their answers back."""
        state = self._require_state()
        assert state.roster is not None, "swarm() fixes the swarm first"
        if self._stop_pause is not None:  # stopped between swarm() and here: nothing goes out
            return Evaluation(evaluation_id, tuple(state.roster), STOP_PAUSE_TEXT)
        # The loop records only the post-evaluation (a replay's too): its robots flash.
        post = record
        attempt = await self.rounds.run(
            evaluation_id=evaluation_id,
            genome=genome,
            spec=self.spec,
            steps=steps,
            step_period=self.experiment.step_period,
            record=record,
            robots=state.roster,
            post_evaluation=post,
            on_sent=self._post_evaluation_sent if post else None,
        )
        if not attempt.ok:
            return Evaluation(evaluation_id, attempt.robots, attempt.failure or "failed")
        for robot in attempt.robots:
            stats = attempt.results[robot].stats
            self._robot_state[robot] = {
                "battery_v": stats.battery_v,
                "overruns": stats.overruns,
                "read_failures": stats.read_failures,
            }
        return Evaluation(
            evaluation_id,
            attempt.robots,
            None,
            fitnesses=attempt.fitnesses(),
            seconds=attempt.completed - attempt.started,
            safety_share=attempt.safety_share(),
            results=dict(attempt.results) if record else None,
            stats=tuple(attempt.results[robot].stats for robot in attempt.robots),
            started_at=attempt.sent_at,
        )

    def _post_evaluation_sent(self, evaluation_id: int, sent_at: float) -> None:
        # Every attempt: a camera filming sees each one's flash, and only the counted one's time
        # goes into post_evaluation.json. A line appended, in the event loop, once per attempt.
        self.log.info("post-evaluation attempt %d went out: the robots flash", evaluation_id)
        try:
            append_event(
                self.run_dir.path,
                Event(time=sent_at, kind=EVENT_POST_EVALUATION, evaluation_id=evaluation_id),
            )
        except OSError as exc:
            self.log.warning("the post-evaluation's start could not be logged: %s", exc)

    async def before_post_evaluation(self) -> None:
        """The ``before_post_evaluation`` hook, if any (a simulator resets its arena)."""
        if self._before_post_evaluation is not None:
            await self._before_post_evaluation()

    async def after_post_evaluation(self, run_dir: RunDir) -> None:
        """Nothing to add: the traces are the run's."""

    def snapshot(self) -> dict[str, Any] | None:
        """A simulator's state for the checkpoint (None for real robots)."""
        return None if self._snapshot is None else self._snapshot()

    async def change_arena(self, event: ArenaEvent, index: int) -> ArenaChange | None:
        """A simulator's world changes (the ``change_arena`` hook); None for real robots,
        whose run pauses for a person to make the change."""
        return None if self._change_arena is None else await self._change_arena(event, index)

    # -- the robots' connections -------------------------------------------------------------

    def _admit(self, robot_id: str) -> tuple[str, str] | None:
        allowed = self.config.allowed_robots
        if allowed and robot_id not in allowed and robot_id not in self._spares:
            return REFUSED_UNKNOWN_ROBOT, f"{robot_id} is not among the allowed robots"
        roster = self.state.roster if self.state is not None else None
        if roster is None and robot_id in self._spares:
            return (
                REFUSED_UNKNOWN_ROBOT,
                f"{robot_id} is a spare: it stands by once the swarm is fixed",
            )
        if roster is not None:
            # Spares (allowed, or one a swap waits for) stand by, to take a gone robot's place.
            spare = bool(allowed) or robot_id in self.swaps.expecting
            if robot_id not in roster and not spare:
                return REFUSED_UNKNOWN_ROBOT, f"{robot_id} is not in this run's swarm"
        elif (
            robot_id not in self.server.sessions
            and len(self.server.sessions) >= self.config.robot_count
        ):
            return REFUSED_UNKNOWN_ROBOT, f"the swarm of {self.config.robot_count} is complete"
        return None

    def _on_join(self, session: Session) -> None:
        self.away.back(session.robot_id)
        self.run_dir.note_software(session.hello, self.log)
        self._swarm_changed.set()
        self.evolution.emit()

    def _on_leave(self, session: Session, reason: str) -> None:
        self.away.left(session.robot_id, self.state.roster if self.state is not None else None)
        self.rounds.on_leave(session, reason)
        self._swarm_changed.set()
        self.evolution.emit()

    def _on_message(self, session: Session, msg: Answer) -> None:
        if isinstance(msg, CheckReport):
            # Only `surprise-master check` asks for one; a robot sending it unasked is ignored.
            self.log.debug("robot %s: an unasked check report ignored", session.robot_id)
            return
        if isinstance(msg, EscapeReply):
            self.escapes.on_reply(session, msg)
            return
        if isinstance(msg, Stopped):
            self.stops.on_reply(session, msg)
            return
        self.rounds.on_message(session, msg)

    def _members(self) -> list[str]:
        """The run's robots: its swarm once fixed, else those it admits (allowed or here)."""
        state = self.state
        if state is not None and state.roster is not None:
            return list(state.roster)
        return list(self.config.allowed_robots or self.connected_robots)

    def _evaluating(self, robot: str) -> bool:
        """Whether ``robot`` runs an evaluation of the current attempt it has not answered."""
        attempt = self.rounds.current
        return (
            attempt is not None
            and not attempt.finished.is_set()
            and robot in attempt.members
            and robot not in attempt.results
        )

    def _fleet_stop(self) -> None:
        """A fleet stop: the running attempt fails (it does not count) and the run pauses before
        the next; the desk stops the motors. A run paused already stays in its pause."""
        if self.evolution.pauses.current is None:
            self._stop_pause = Pause("fleet-stop", STOP_PAUSE_TEXT)
        if self.rounds.current is not None:
            self.rounds.current.fail(STOP_PAUSE_TEXT)
        self._swarm_changed.set()

    def _paused(self) -> str | None:
        pause = self.evolution.pauses.current
        return None if pause is None else pause.text

    # -- progress ----------------------------------------------------------------------------

    @property
    def elapsed_s(self) -> float:
        """Wall-clock seconds this run has been served, over all its resumptions."""
        return self.evolution.elapsed_s

    @property
    def progress(self) -> Progress:
        """A snapshot of where the run stands."""
        return self.evolution.progress

    def _robots_text(self) -> str:
        missing = self.missing_robots()
        return f"{self.robots_connected}/{self.robots_expected} connected" + (
            f", missing {', '.join(missing)}" if missing else ""
        )

    def _publish_status(self, progress: Progress, *, online: bool = True) -> None:
        """Progress listener: the retained ``<prefix>/run/status``. Only queues (latest wins)."""
        if self.telemetry is None:
            return
        status = run_status(progress, self.connected_robots, online=online)
        self.telemetry.publish_nowait(run_status_suffix(), status, retain=True)

    # -- live.json ---------------------------------------------------------------------------

    def _live_data(self, *, running: bool) -> Live:
        state = self._require_state()
        pause = self.evolution.pauses.current
        return Live(
            pid=os.getpid(),
            running=running,
            host=self.host,
            port=self.port,
            robots=list(self.connected_robots),
            phase=state.phase,
            waiting=self._waiting,
            evaluations=state.optimizer.evaluations,
            time_left_s=self.evolution.time_left(),
            paused=None if pause is None else pause.note(),
            robot_state=dict(self._robot_state),
            updated_at=time.time(),
        )

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
