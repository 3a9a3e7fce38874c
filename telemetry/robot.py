"""A robot's telemetry: per-evaluation summaries and rate-limited step samples.

The agent's runner holds a :class:`RobotTelemetry` and, per evaluation, hands the control loop the
:meth:`StepSampler.sample` of a fresh :class:`StepSampler`. The loop calls it once per step with
references to that step's arrays; on all but every ``every``-th step it returns after one integer
test, and on the others it copies the few small arrays into a payload and queues it with
:meth:`~telemetry.publisher.TelemetryPublisher.publish_nowait`. Formatting and publishing happen
later in the publisher's task, never in the step.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Final

import numpy as np

from telemetry.payloads import DECIMALS, EvaluationSummary, StepSample, now, robot_suffix
from telemetry.publisher import TelemetryPublisher

__all__ = ["EVALUATION_QOS", "RobotTelemetry", "StepSampler", "steps_between_samples"]

log = logging.getLogger(__name__)

#: QoS of evaluation summaries: one every evaluation, each worth an acknowledgement. Samples use
#: QoS 0: a lost one is replaced by the next within half a second.
EVALUATION_QOS: Final = 1


def steps_between_samples(rate_hz: float, period: float) -> int | None:
    """Control steps between two samples for ``rate_hz`` at ``period`` seconds per step (at least
    1: never more than one sample per step), or None when ``rate_hz`` is 0 (no samples)."""
    if rate_hz <= 0:
        return None
    return max(1, round(1.0 / (rate_hz * period)))


class StepSampler:
    """Turns every ``every``-th control step of one evaluation into a :class:`StepSample`.

    A sample at step t holds s(t), the command, the safety reason and p(t), the prediction made
    at step t-1; so the sampler also copies the prediction of the step before each sample step.
    Never raises into the loop.
    """

    __slots__ = ("_held", "_held_step", "_publisher", "_suffix", "evaluation", "every", "names")

    def __init__(
        self,
        publisher: TelemetryPublisher,
        suffix: str,
        evaluation: int,
        names: tuple[str, ...],
        every: int,
    ) -> None:
        if every < 1:
            raise ValueError("every must be at least 1")
        self._publisher = publisher
        self._suffix = suffix
        self.evaluation = evaluation
        self.names = names
        self.every = every
        self._held: np.ndarray | None = None
        self._held_step = -1

    def sample(
        self,
        step: int,
        sensors: np.ndarray,
        predictions: np.ndarray,
        command: tuple[float, float],
        reason: str | None,
    ) -> None:
        """Called by the control loop after the safety layer, with step t (from 1), s(t),
        p(t+1), the command to apply and the safety reason. Arrays are copied when kept, since
        the loop reuses its buffers."""
        every = self.every
        if step % every == 0:
            try:
                held = self._held if self._held_step == step - 1 else None
                self._publisher.publish_nowait(
                    self._suffix,
                    StepSample(
                        t=now(),
                        evaluation=self.evaluation,
                        step=step,
                        names=self.names,
                        sensors=sensors.copy(),
                        predictions=held,
                        command=(
                            round(float(command[0]), DECIMALS),
                            round(float(command[1]), DECIMALS),
                        ),
                        reason=reason,
                    ),
                )
            except Exception:  # a telemetry bug must not fail an evaluation
                log.exception("telemetry: step sample %d failed; sampling stops", step)
                self.every = 1 << 62  # no further samples this evaluation
        if (step + 1) % every == 0:
            self._held = predictions.copy()
            self._held_step = step


class RobotTelemetry:
    """What one robot's agent publishes: ``robot/<id>/evaluation`` and ``robot/<id>/sample``.

    The publisher's lifecycle (start, close) belongs to the agent.
    """

    def __init__(self, publisher: TelemetryPublisher, robot_id: str) -> None:
        self.publisher = publisher
        self.robot_id = robot_id
        self._evaluation_suffix = robot_suffix(robot_id, "evaluation")
        self._sample_suffix = robot_suffix(robot_id, "sample")

    def sampler(self, evaluation: int, names: tuple[str, ...], period: float) -> StepSampler | None:
        """A fresh sampler for one evaluation over the sensors ``names`` whose steps take
        ``period`` seconds (to turn ``rate_hz`` into steps); None when no samples are wanted."""
        every = steps_between_samples(self.publisher.config.rate_hz, period)
        if every is None:
            return None
        return StepSampler(self.publisher, self._sample_suffix, evaluation, names, every)

    def evaluation(
        self,
        evaluation: int,
        *,
        requested: int,
        steps: int,
        fitness: float | None,
        failure: str | None = None,
        interventions: Mapping[str, int] | None = None,
        overruns: int = 0,
        read_failures: int = 0,
        battery_v: float | None = None,
        duration_s: float | None = None,
    ) -> None:
        """Queue the summary of one evaluation (never raises, never waits)."""
        try:
            summary = EvaluationSummary(
                t=now(),
                evaluation=evaluation,
                requested=requested,
                steps=steps,
                fitness=None if fitness is None else float(fitness),
                failure=failure,
                interventions=dict(interventions or {}),
                overruns=overruns,
                read_failures=read_failures,
                battery_v=battery_v,
                duration_s=None if duration_s is None else round(duration_s, 3),
            )
        except Exception:
            log.exception("telemetry: cannot summarise evaluation %d", evaluation)
            return
        self.publisher.publish_nowait(self._evaluation_suffix, summary, qos=EVALUATION_QOS)
