"""The control loop: the steps of one evaluation at a fixed period on absolute deadlines.

One step (docs/robot-agent.md, "One control step")::

    read s(t) (bounded by a timeout) -> score p(t), made at t-1, against s(t)
    -> actor a(t) from s(t), a(t-1) -> predictor p(t+1) from s(t), a(t)
    -> safety: the command to apply -> drive -> feed the watchdog -> sleep to the next deadline

Timing: with ``t0 = clock.now()`` at the start, step k must end by ``t0 + (k + 1) * period``, where
the period is the evaluation's (the experiment's ``step_period``, sent in each Evaluate). The
deadline is computed from ``t0`` every time, never by adding periods, so it cannot drift. A step
that ends after its deadline counts as an overrun and the next step starts at once, in the period
it is already in: later steps stay on the original grid and a long stall does not cause a burst of
catch-up steps.

A failed or timed-out read is not fatal at once: the motors stop for that step (the safety layer
treats the frame as stale), the prediction waiting for that reading is dropped rather than scored
against a later one, and the loop carries on. ``max_read_failures`` failures in a row end the
evaluation with a reason. Steps without a reading do not appear in the trace.

Everything that can be is prepared once per evaluation (:class:`ControlLoop` per agent, the sensor
index map per evaluation); a step allocates only what numpy needs and logs nothing.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

import numpy as np

from drivers.body import Body
from drivers.clock import Clock
from minimize_surprise.errors import HardwareTimeoutError, RobotUnreachableError
from minimize_surprise.fitness import SurpriseScore
from minimize_surprise.network import NetworkPair
from minimize_surprise.safety import REASON_EXPERIMENTER, STOP, SafetyLayer, SafetyState
from minimize_surprise.wire import EvaluationStats, Trace
from robot_agent.led import StartFlash
from robot_agent.watchdog import Watchdog

__all__ = [
    "FAILED_UNREACHABLE",
    "ControlLoop",
    "Deadlines",
    "LoopOutcome",
    "MissingSensorsError",
    "StepSink",
    "sensor_index",
]

log = logging.getLogger(__name__)

#: Failed reasons of evaluations that ended because the robot cannot be reached (the body raised
#: :class:`~minimize_surprise.errors.RobotUnreachableError`) start with this word.
FAILED_UNREACHABLE = "robot-unreachable"

#: Called after the safety layer on every step that had a reading, with (step from 1, s(t),
#: p(t+1), the command to apply, the safety reason). It runs inside the step: it must return at
#: once and copy what it keeps (the loop reuses its sensor buffer). Telemetry's sampler is one.
StepSink = Callable[[int, np.ndarray, np.ndarray, tuple[float, float], str | None], None]


class MissingSensorsError(ValueError):
    """The experiment needs sensors the body lacks; ``missing`` names them."""

    def __init__(self, missing: list[str]) -> None:
        self.missing = missing
        super().__init__(f"the body lacks the sensor(s) {', '.join(missing)}")


def sensor_index(needed: tuple[str, ...], available: tuple[str, ...]) -> np.ndarray | None:
    """Positions in a body frame of the sensors ``needed``, in ``needed``'s order.

    Returns None when the frame already is in that order (no copy needed per step). Raises
    :class:`MissingSensorsError` naming every sensor the body lacks.
    """
    where = {name: i for i, name in enumerate(available)}
    missing = [name for name in needed if name not in where]
    if missing:
        raise MissingSensorsError(missing)
    index = np.array([where[name] for name in needed], dtype=np.intp)
    if len(needed) == len(available) and (index == np.arange(len(available))).all():
        return None
    return index


#: Seconds past its deadline a step still counts as on time: deadlines computed as t0 + k * period
#: and a clock that adds up its steps (a simulated one) differ by rounding, 1e-16 s, which made
#: every simulated run report overruns that never happened. A real overrun is milliseconds.
DEADLINE_SLACK: Final = 1e-9


class Deadlines:
    """Absolute deadlines ``t0 + (k + 1) * period`` on a :class:`Clock`, with overrun counting.

    Call :meth:`start` when the first step begins and :meth:`wait` at the end of every step.
    """

    def __init__(self, clock: Clock, period: float) -> None:
        if not period > 0:
            raise ValueError("period must be positive")
        self.clock = clock
        self.period = period
        self.t0 = 0.0
        #: index of the period the current step runs in; its deadline is t0 + (slot + 1) * period
        self.slot = 0
        #: steps that ended after their deadline
        self.overruns = 0

    def start(self) -> None:
        """Begin the grid now: the current step's deadline is one period from now."""
        self.t0 = self.clock.now()
        self.slot = 0
        self.overruns = 0

    @property
    def deadline(self) -> float:
        """When the current step must end."""
        return self.t0 + (self.slot + 1) * self.period

    async def wait(self) -> None:
        """End the current step: sleep to its deadline, or count an overrun and return at once."""
        deadline = self.t0 + (self.slot + 1) * self.period
        now = self.clock.now()
        if now <= deadline + DEADLINE_SLACK:
            await self.clock.sleep_until(deadline)
            self.slot += 1
            return
        self.overruns += 1
        # Start the next step at once, in the period we are already in; its deadline is that
        # period's end, so the grid is kept. The loop guards against rounding in the division.
        slot = max(self.slot + 1, math.floor((now - self.t0) / self.period))
        while self.t0 + (slot + 1) * self.period <= now:
            slot += 1
        self.slot = slot


@dataclass(slots=True)
class LoopOutcome:
    """What one run of the loop produced.

    ``failure`` is None when every step ran; otherwise it says why the loop ended early (and
    ``fitness``/``trace`` cover the steps that ran). ``safety_state`` is the state after the last
    step, to carry the escape generator over to the next evaluation.
    """

    fitness: float
    stats: EvaluationStats
    trace: Trace | None
    safety_state: SafetyState
    failure: str | None = None


class ControlLoop:
    """Runs evaluations on one body: the per-step work of one control step (docs/robot-agent.md).

    ``layer`` is the safety layer for ``body.sensors`` (it sees every sensor of the body, not just
    the experiment's). ``watchdog``, if given, is fed every step and checked before every drive;
    the caller arms and disarms it. The motors are *not* stopped here at the end: the caller
    (:class:`~robot_agent.runner.EvaluationRunner`) does that on every exit path.
    """

    def __init__(
        self,
        body: Body,
        clock: Clock,
        layer: SafetyLayer,
        *,
        read_timeout: float = 0.15,
        max_read_failures: int = 3,
        drive_timeout: float = 0.5,
        watchdog: Watchdog | None = None,
    ) -> None:
        if tuple(layer.sensors) != tuple(body.sensors):
            raise ValueError("the safety layer must be built for the body's sensors")
        self.body = body
        self.clock = clock
        self.layer = layer
        self.read_timeout = read_timeout
        self.max_read_failures = max_read_failures
        self.drive_timeout = drive_timeout
        self.watchdog = watchdog
        #: the deadlines of the evaluation running now (or the last one)
        self.deadlines: Deadlines | None = None
        #: the experimenter asked for an escape (``surprise-master escape``): passed to the safety
        #: layer at every step with a usable reading until the layer starts it; the runner sets
        #: it and clears it around every evaluation, so none carries over
        self.escape_requested = False
        #: the steps at which the experimenter's escapes started in the latest evaluation
        self.escapes_started: list[int] = []
        # Passed to the safety layer for a step without a reading; it only checks the shape.
        self._no_values = np.zeros(len(body.sensors))
        self._has_pose = hasattr(body, "pose")

    async def run(
        self,
        network: NetworkPair,
        index: np.ndarray | None,
        steps: int,
        state: SafetyState,
        *,
        period: float = 0.1,
        record: bool = False,
        sink: StepSink | None = None,
        flash: StartFlash | None = None,
    ) -> LoopOutcome:
        """Run ``steps`` control steps of ``period`` seconds of ``network`` (already reset) from
        where the robot stands.

        ``index`` maps a body frame to the network's sensor order (see :func:`sensor_index`);
        ``state`` is the safety state to start from; ``sink`` (optional) sees every step with a
        reading (see :data:`StepSink`); ``flash`` (optional) is lit at the first step and put
        out at the step its time is up (the caller finishes it). Exceptions of the body's
        ``drive`` and of the network propagate, as does cancellation; the motors keep their last
        command then.
        """
        # Locals: attribute look-ups add up at 10 Hz on a Pi; this is the hot path.
        body, clock, layer, watchdog = self.body, self.clock, self.layer, self.watchdog
        read_timeout, drive_timeout = self.read_timeout, self.drive_timeout
        has_pose = self._has_pose
        # A timeout costs a timer per call; a body that never waits for I/O cannot hang.
        blocking = body.blocking
        score = SurpriseScore()
        sensors = np.empty(network.layout.sensors) if index is not None else None
        interventions: dict[str, int] = {}
        read_failures = consecutive_failures = 0
        drop_pending = False
        failure: str | None = None
        # A recording fills preallocated rows (a recorded evaluation is at most
        # MAX_RECORDED_STEPS long, so at most a few MB); ``recorded`` counts the rows filled.
        width = network.layout.sensors
        rows = steps if record else 0
        trace_sensors = np.empty((rows, width))
        trace_predictions = np.empty((rows, width))
        trace_actions = np.empty((rows, 2))
        trace_commands = np.empty((rows, 2))
        trace_poses = np.empty((rows if has_pose else 0, 3))
        trace_safety: list[str] = []
        recorded = 0

        deadlines = self.deadlines = Deadlines(clock, period)
        deadlines.start()
        self.escapes_started = []
        if flash is not None:
            await flash.start()  # never raises, never waits for the robot
        step = 0
        while step < steps:
            step += 1
            if watchdog is not None:
                watchdog.feed()
            if flash is not None and flash.until is not None:
                await flash.step()
            # --- read s(t), bounded
            error: str | None = None
            try:
                if blocking:
                    async with asyncio.timeout(read_timeout):
                        frame = await body.read()
                else:
                    frame = await body.read()
                values = frame.values
                # With an index, np.take fills ``sensors`` and returns it.
                s = np.take(values, index, out=sensors) if index is not None else values
                if not np.isfinite(s).all():
                    error = "the reading holds a non-finite value"
            except TimeoutError:
                error = f"no reading within {read_timeout} s"
            except RobotUnreachableError as exc:
                # Gone for longer than an evaluation lasts: no point in counting to the limit.
                read_failures += 1
                failure = f"{FAILED_UNREACHABLE}: {exc}"
                break
            except Exception as exc:  # any failing read is a lost reading, counted below
                error = f"read failed: {exc!r}"

            if error is not None:
                read_failures += 1
                consecutive_failures += 1
                # The pending prediction was made for this missed reading; scoring it against a
                # later one would measure something else.
                drop_pending = True
                decision = layer.step(state, self._no_values, STOP, fresh=False)
                reason = decision.reason
                if reason is not None:
                    interventions[reason] = interventions.get(reason, 0) + 1
                if consecutive_failures >= self.max_read_failures:
                    failure = (
                        f"sensor-read: {consecutive_failures} reads in a row failed (last: {error})"
                    )
                    break
                command = decision.command
            else:
                consecutive_failures = 0
                # --- score p(t) against s(t), then a(t) and p(t+1)
                if drop_pending:
                    drop_pending = False  # expect() below replaces the stale prediction
                else:
                    score.observe(s)
                action, prediction = network.step(s)
                score.expect(prediction)
                # --- safety: on the whole frame, with the frame's age on the loop's clock
                decision = layer.step(
                    state,
                    values,
                    action,
                    age=clock.now() - frame.timestamp,
                    escape_now=self.escape_requested,
                )
                state = decision.state
                reason = decision.reason
                if reason == REASON_EXPERIMENTER:
                    # Used up: the layer runs the rest of the manoeuvre on its own. Rare enough
                    # (a person's hand) to be logged from inside a step.
                    self.escape_requested = False
                    self.escapes_started.append(step)
                    log.info("the experimenter's escape started at step %d", step)
                if reason is not None:
                    interventions[reason] = interventions.get(reason, 0) + 1
                command = decision.command
                if sink is not None:
                    sink(step, s, prediction, command, reason)
                if record:
                    trace_sensors[recorded] = s
                    trace_predictions[recorded] = prediction
                    trace_actions[recorded] = action
                    trace_commands[recorded] = command
                    trace_safety.append(reason or "")
                    if has_pose:
                        trace_poses[recorded] = body.pose  # type: ignore[attr-defined]
                    recorded += 1

            # --- drive, unless the watchdog has taken over
            if watchdog is not None and watchdog.tripped:
                failure = f"watchdog: {watchdog.tripped_reason}"
                break
            if blocking:
                try:
                    async with asyncio.timeout(drive_timeout):
                        await body.drive(command[0], command[1])
                except TimeoutError:
                    raise HardwareTimeoutError("drive", drive_timeout) from None
            else:
                await body.drive(command[0], command[1])
            if watchdog is not None:
                watchdog.feed()
            # --- sleep to the next absolute deadline
            await deadlines.wait()

        steps_run = step if failure is None else step - 1
        stats = EvaluationStats(
            steps_run=steps_run,
            overruns=deadlines.overruns,
            interventions=interventions,
            read_failures=read_failures,
        )
        trace = None
        if record:
            trace = Trace.from_arrays(
                sensors=trace_sensors[:recorded],
                predictions=trace_predictions[:recorded],
                actions=trace_actions[:recorded],
                commands=trace_commands[:recorded],
                safety=trace_safety,
                poses=trace_poses[:recorded] if has_pose else None,
            )
        return LoopOutcome(
            fitness=float(score.fitness),
            stats=stats,
            trace=trace,
            safety_state=state,
            failure=failure,
        )
