"""One evaluation on the robot: from an ``Evaluate`` message to a ``Result`` or ``Failed``.

:class:`EvaluationRunner` checks the request (genome, sensors), builds the network pair, resets
the safety escape state and the network's memory (a new genome; the robot's pose is not reset),
arms the watchdog, runs the :class:`~robot_agent.loop.ControlLoop` and, on every exit path (end,
failure, exception, cancellation), stops the motors and disarms the watchdog.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import TYPE_CHECKING, Final

import msgspec
import numpy as np

from drivers.body import Body
from drivers.clock import Clock
from minimize_surprise.errors import HardwareError, ProtocolError, RobotUnreachableError
from minimize_surprise.network import NetworkPair
from minimize_surprise.safety import SafetyConfig, SafetyLayer
from minimize_surprise.wire import (
    ESCAPE_REFUSED_IDLE,
    ESCAPE_REFUSED_PROFILE,
    MAX_BATTERY_V,
    CheckReport,
    EscapeReply,
    Evaluate,
    EvaluationStats,
    Failed,
    Result,
    Stopped,
    genome_from_bytes,
)
from robot_agent.bounded import finish
from robot_agent.checkup import check_body
from robot_agent.config import MAX_PERIOD, LoopConfig
from robot_agent.led import StartFlash
from robot_agent.loop import (
    FAILED_UNREACHABLE,
    ControlLoop,
    LoopOutcome,
    MissingSensorsError,
    sensor_index,
)
from robot_agent.watchdog import Watchdog
from telemetry.robot import RobotTelemetry

if TYPE_CHECKING:
    from robot_agent.health import RobotHealth

__all__ = [
    "FAILED_GENOME",
    "FAILED_HARDWARE",
    "FAILED_INTERNAL",
    "FAILED_MISSING_SENSORS",
    "FAILED_PERIOD",
    "FAILED_STEPS",
    "FAILED_UNREACHABLE",
    "EvaluationRunner",
    "stop_motors",
]

log = logging.getLogger(__name__)

# Failed reasons start with one of these words (then ": " and the details), so the master can
# group failures without parsing prose. The loop adds "sensor-read", "watchdog" and
# FAILED_UNREACHABLE ("robot-unreachable").
#: the spec needs a sensor the body does not have
FAILED_MISSING_SENSORS = "missing-sensors"
#: the genome does not fit the spec
FAILED_GENOME = "genome"
#: the step period is one this robot cannot keep (see LoopConfig.min_period and MAX_PERIOD)
FAILED_PERIOD = "period"
#: more steps than this robot runs in one evaluation (LoopConfig.max_steps)
FAILED_STEPS = "steps"
#: a motor write failed or hung
FAILED_HARDWARE = "hardware"
#: a bug (an unexpected exception); the log holds the traceback
FAILED_INTERNAL = "internal"
#: Seconds the battery read after an evaluation may take: a present robot answers one
#: ``GetVariable`` within a sensor period (0.1 s). An unread battery is reported unknown and
#: never fails the evaluation (the motor stop's read-back already proved the robot is there).
BATTERY_READ_TIMEOUT: Final = 1.0


async def stop_motors(body: Body, timeout: float) -> BaseException | None:
    """Stop the motors (see :func:`~robot_agent.bounded.finish`); returns None if that is known to
    have worked, else the error (logged)."""
    error = await finish(body.stop(), timeout)
    if error is not None:
        log.error("stopping the motors failed: %r", error)
    return error


class EvaluationRunner:
    """Runs evaluations on one body; one at a time (a second :meth:`run` waits for the first).

    ``loop`` and ``safety`` are the agent's settings; ``watchdog`` (optional) is armed for the
    duration of each evaluation; ``safety_seed`` seeds the safety layer's escape turns (use a
    different one per robot); ``telemetry`` (optional) receives a summary of every evaluation
    and hands the control loop its step sampler; ``health`` (optional) is told when the robot
    cannot be reached, and while it cannot, evaluations fail at once with its reason.
    """

    def __init__(
        self,
        body: Body,
        clock: Clock,
        *,
        loop: LoopConfig | None = None,
        safety: SafetyConfig | None = None,
        watchdog: Watchdog | None = None,
        safety_seed: int = 0,
        telemetry: RobotTelemetry | None = None,
        health: RobotHealth | None = None,
    ) -> None:
        self.body = body
        self.health = health
        self.telemetry = telemetry
        self.clock = clock
        self.config = loop if loop is not None else LoopConfig()
        self.watchdog = watchdog
        self.layer = SafetyLayer(body.sensors, safety)
        self.safety_state = self.layer.initial_state(safety_seed)
        self.loop = ControlLoop(
            body,
            clock,
            self.layer,
            read_timeout=self.config.read_timeout,
            max_read_failures=self.config.max_read_failures,
            drive_timeout=self.config.stop_timeout,
            watchdog=watchdog,
        )
        self._lock = asyncio.Lock()
        #: the id of the evaluation running now, if any
        self.running: int | None = None

    def prepare(self, msg: Evaluate) -> tuple[NetworkPair, np.ndarray | None] | Failed:
        """The network and sensor index for ``msg``, or the Failed to answer if it cannot run."""
        config = self.config
        if not config.min_period <= msg.step_period <= MAX_PERIOD:
            return Failed(
                evaluation_id=msg.evaluation_id,
                reason=f"{FAILED_PERIOD}: this robot runs steps of {config.min_period:g} s to "
                f"{MAX_PERIOD:g} s (its sensors' update rate, loop.min_period, and its watchdog), "
                f"not {msg.step_period:g} s",
            )
        if msg.steps > config.max_steps:
            return Failed(
                evaluation_id=msg.evaluation_id,
                reason=f"{FAILED_STEPS}: this robot runs at most {config.max_steps} steps in one "
                f"evaluation (loop.max_steps), not {msg.steps}",
            )
        try:
            index = sensor_index(msg.spec.sensors, self.body.sensors)
        except MissingSensorsError as exc:
            return Failed(
                evaluation_id=msg.evaluation_id, reason=f"{FAILED_MISSING_SENSORS}: {exc}"
            )
        try:
            network = NetworkPair(msg.spec, genome_from_bytes(msg.genome))
        except (ProtocolError, ValueError) as exc:  # GenomeError is a ValueError
            return Failed(evaluation_id=msg.evaluation_id, reason=f"{FAILED_GENOME}: {exc}")
        return network, index

    async def run(self, msg: Evaluate) -> Result | Failed:
        """Run ``msg.genome`` for ``msg.steps`` steps from where the robot stands.

        Returns the :class:`Result` (with a trace if ``msg.record``) or a :class:`Failed` whose
        reason starts with a ``FAILED_*`` word, ``sensor-read`` or ``watchdog``: among them a
        ``step_period`` outside [``loop.min_period``, :data:`MAX_PERIOD`] or more steps than
        ``loop.max_steps``. The motors are
        stopped and the watchdog disarmed on every exit path, cancellation included.
        """
        prepared = self.prepare(msg)
        if isinstance(prepared, Failed):
            log.warning("evaluation %d refused: %s", msg.evaluation_id, prepared.reason)
            self._summarise(msg, prepared, None, None)
            return prepared
        if self.health is not None and not self.health.reachable:
            failed = Failed(evaluation_id=msg.evaluation_id, reason=self.health.failure())
            log.warning("evaluation %d not run: %s", msg.evaluation_id, failed.reason)
            self._summarise(msg, failed, None, None)
            return failed
        network, index = prepared
        async with self._lock:
            # An experimenter's escape asked for during an earlier evaluation does not carry over.
            self.loop.escape_requested = False
            self.running = msg.evaluation_id
            # A new genome: no escape manoeuvre carries over (the network was just built fresh).
            state = self.layer.reset(self.safety_state)
            log.info(
                "evaluation %d: %d steps of %g s%s",
                msg.evaluation_id,
                msg.steps,
                msg.step_period,
                " (recorded)" * msg.record,
            )
            failure: str | None = None
            unreachable: str | None = None
            outcome: LoopOutcome | None = None
            telemetry = self.telemetry
            # Telemetry's sampler rate-limits and copies; it never formats or sends in a step.
            sampler = None
            if telemetry is not None:
                sampler = telemetry.sampler(msg.evaluation_id, msg.spec.sensors, msg.step_period)
            started = self.clock.now()
            # The post-evaluation's start flash, for an overhead camera (robot_agent.led).
            flash = StartFlash(self.body, self.clock) if msg.post_evaluation else None
            if self.watchdog is not None:
                self.watchdog.arm()
            try:
                outcome = await self.loop.run(
                    network,
                    index,
                    msg.steps,
                    state,
                    period=msg.step_period,
                    record=msg.record,
                    sink=None if sampler is None else sampler.sample,
                    flash=flash,
                )
            except RobotUnreachableError as exc:
                unreachable = str(exc)
            except HardwareError as exc:
                failure = f"{FAILED_HARDWARE}: {exc}"
            except Exception as exc:  # a bug must not leave the robot driving or kill the agent
                log.exception("evaluation %d crashed", msg.evaluation_id)
                failure = f"{FAILED_INTERNAL}: {exc!r}"
            finally:
                self.running = None
                self.loop.escape_requested = False
                # The stop is confirmed by the robot itself; a robot that does not confirm it
                # is unreachable, whatever the evaluation looked like (the master must know).
                stop_error = await stop_motors(self.body, self.config.stop_timeout)
                if stop_error is not None:
                    if self.watchdog is not None:
                        await finish(self.watchdog.trip("stop failed"), self.config.stop_timeout)
                    if isinstance(stop_error, RobotUnreachableError | TimeoutError):
                        unreachable = unreachable or f"the motor stop: {stop_error}"
                if self.watchdog is not None:
                    self.watchdog.disarm()
                if flash is not None:
                    # After the motors: an LED never delays a stop. Bounded; never raises.
                    await flash.finish()

        if outcome is not None:
            self.safety_state = outcome.safety_state
            failure = outcome.failure
            if failure is None and not 0.0 <= outcome.fitness <= 1.0:
                # The master refuses it (a protocol error that would cost the session): say why
                # instead. A body reporting values outside [0, 1] leads here, as would a bug.
                failure = f"{FAILED_INTERNAL}: fitness {outcome.fitness} outside [0, 1]"
            if failure is not None and failure.startswith(f"{FAILED_UNREACHABLE}:"):
                unreachable = unreachable or failure.partition(": ")[2]
        if unreachable is not None:
            failure = f"{FAILED_UNREACHABLE}: {unreachable}"
            if self.health is not None:
                self.health.lost(unreachable)
        duration = self.clock.now() - started
        if failure is not None:
            log.warning("evaluation %d failed: %s", msg.evaluation_id, failure)
            failed = Failed(evaluation_id=msg.evaluation_id, reason=failure)
            self._summarise(msg, failed, outcome.stats if outcome else None, duration)
            return failed
        assert outcome is not None
        stats = outcome.stats
        battery = await self._read_battery()
        if battery is not None:
            stats = msgspec.structs.replace(stats, battery_v=battery)
        log.info(
            "evaluation %d: fitness %.4f, %d overruns, %d read failures, interventions %s, "
            "battery %s",
            msg.evaluation_id,
            outcome.fitness,
            stats.overruns,
            stats.read_failures,
            stats.interventions or "none",
            "unknown" if stats.battery_v is None else f"{stats.battery_v:.2f} V",
        )
        result = Result(
            evaluation_id=msg.evaluation_id,
            fitness=outcome.fitness,
            stats=stats,
            trace=outcome.trace,
        )
        self._summarise(msg, result, stats, duration)
        return result

    def request_escape(self, seq: int) -> EscapeReply:
        """The experimenter asks for the safety layer's escape now (``surprise-master escape``):
        accepted while an evaluation runs in the ``escape`` profile (the layer starts it at the
        next step with a usable reading), refused otherwise with a reason starting with
        ``ESCAPE_REFUSED_PROFILE`` or ``ESCAPE_REFUSED_IDLE`` (:mod:`minimize_surprise.wire`).
        Only asks; the layer decides the motors."""
        if self.layer.config.profile != "escape":
            return EscapeReply(
                seq=seq,
                accepted=False,
                reason=f"{ESCAPE_REFUSED_PROFILE}: this robot's safety layer runs the "
                f"{self.layer.config.profile!r} profile, which has no escape behaviour (paper "
                "Sec. V-B): move the robot by hand",
            )
        running = self.running
        if running is None:
            return EscapeReply(
                seq=seq,
                accepted=False,
                reason=f"{ESCAPE_REFUSED_IDLE}: no evaluation runs, the motors are stopped",
            )
        self.loop.escape_requested = True
        return EscapeReply(seq=seq, accepted=True, evaluation_id=running)

    async def stop_all(self, seq: int, cancelled: int | None) -> Stopped:
        """``surprise-master fleet stop``: the motors stopped now, after the link cancelled
        evaluation ``cancelled`` (None: none ran). Never refused: the stop is written even when
        nothing ran, and the answer says whether the robot confirmed it. A stop that fails trips
        the watchdog, which retries it until the robot takes it. The motors stay stopped: only
        an evaluation drives them, and the next one is the master's go-on."""
        error = await stop_motors(self.body, self.config.stop_timeout)
        if error is None:
            return Stopped(seq=seq, confirmed=True, evaluation_id=cancelled)
        if self.watchdog is not None:
            await finish(self.watchdog.trip("fleet stop failed"), self.config.stop_timeout)
        detail = f"the motor stop: {error!r}"[:300]
        return Stopped(seq=seq, confirmed=False, evaluation_id=cancelled, detail=detail)

    async def check(self, seq: int) -> CheckReport:
        """A preflight check's report (:mod:`robot_agent.checkup`); ``busy`` while an
        evaluation runs, which it never disturbs."""
        if self._lock.locked():
            return CheckReport(seq=seq, time=time.time(), busy=True)
        async with self._lock:
            return await check_body(self.body, self.layer, self.safety_state, seq)

    async def _read_battery(self) -> float | None:
        try:
            async with asyncio.timeout(BATTERY_READ_TIMEOUT):
                volts = await self.body.read_battery()
        except Exception as exc:  # an unknown battery, never a failed evaluation
            log.warning("the battery could not be read: %r", exc)
            return None
        # The wire's bounds; a reading outside them is a broken one, reported as unknown.
        if volts is None or not 0.0 <= volts <= MAX_BATTERY_V:
            return None
        return float(volts)

    def _summarise(
        self,
        msg: Evaluate,
        outcome: Result | Failed,
        stats: EvaluationStats | None,
        duration: float | None,
    ) -> None:
        # Queued for the publisher's task; returns at once and never raises.
        if self.telemetry is None:
            return
        self.telemetry.evaluation(
            msg.evaluation_id,
            requested=msg.steps,
            steps=stats.steps_run if stats is not None else 0,
            fitness=outcome.fitness if isinstance(outcome, Result) else None,
            failure=outcome.reason if isinstance(outcome, Failed) else None,
            interventions=stats.interventions if stats is not None else None,
            overruns=stats.overruns if stats is not None else 0,
            read_failures=stats.read_failures if stats is not None else 0,
            battery_v=stats.battery_v if stats is not None else None,
            duration_s=duration,
        )
