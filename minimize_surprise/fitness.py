"""The surprise fitness (paper Eq. 1): how well a robot's predictions came true.

A robot's fitness is the mean over scored steps and sensors of ``1 - |p - s|``, where the
prediction made at step t-1 is scored against the reading at step t (so an evaluation of T steps
scores T - 1 of them). The swarm's fitness is the mean of its robots' fitnesses. Both lie in [0, 1].
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from minimize_surprise.jit import kernel


@kernel(inline=True)
def step_score(prediction: np.ndarray, sensors: np.ndarray) -> float:
    """``1 - mean |p - s|`` over the sensors of one robot and step, summed in sensor order (the
    kernel the engine runs too, so agent and engine agree to the last bit)."""
    total = 0.0
    for i in range(sensors.shape[0]):
        total += abs(prediction[i] - sensors[i])
    return 1.0 - total / sensors.shape[0]


class SurpriseScore:
    """Running score of one robot (or a batch of robots) over an evaluation.

    Per step, call :meth:`observe` with the new readings s(t) *before* predicting, then
    :meth:`expect` with the predictions p(t+1) made at that step. ``fitness`` is the mean of
    ``1 - |p - s|`` over the scored steps and sensors; it is 0.0 before any step was scored.
    """

    _pending: np.ndarray | None
    _total: np.ndarray | float
    scored_steps: int

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget everything: the next :meth:`observe` scores nothing."""
        self._pending = None
        self._total = 0.0
        self.scored_steps = 0

    def observe(self, sensors: np.ndarray) -> np.ndarray | float | None:
        """Score the pending prediction against ``sensors``; returns that step's score or None."""
        if self._pending is None:
            return None
        pending = self._pending
        sensors = np.asarray(sensors, dtype=np.float64)
        if pending.ndim == 1:
            step: np.ndarray | float = step_score(pending, sensors)
        else:
            step = np.array([step_score(p, s) for p, s in zip(pending, sensors, strict=True)])
        self._total = self._total + step
        self.scored_steps += 1
        self._pending = None
        return step

    def expect(self, predictions: np.ndarray) -> None:
        """Remember the predictions p(t+1) to score against the next readings."""
        self._pending = np.array(predictions, dtype=np.float64)

    @property
    def fitness(self) -> np.ndarray | float:
        """Mean score per scored step (per robot for a batch)."""
        if self.scored_steps == 0:
            return 0.0
        return self._total / self.scored_steps


def surprise_fitness(predictions: np.ndarray, sensors: np.ndarray) -> float:
    """Fitness of one recorded evaluation: ``predictions[t]`` (made at t) is scored against
    ``sensors[t + 1]``. Both arrays are shaped ``(T, R)``."""
    predictions = np.asarray(predictions, dtype=np.float64)
    sensors = np.asarray(sensors, dtype=np.float64)
    if predictions.shape != sensors.shape or predictions.ndim != 2:
        raise ValueError("predictions and sensors must both be shaped (steps, sensors)")
    if len(sensors) < 2:
        return 0.0
    return float(np.mean(1.0 - np.abs(predictions[:-1] - sensors[1:])))


def swarm_fitness(robot_fitnesses: Sequence[float] | np.ndarray) -> float:
    """The swarm's fitness: the mean of its robots' fitnesses, with equal weight."""
    values = np.asarray(robot_fitnesses, dtype=np.float64)
    if values.size == 0:
        raise ValueError("a swarm fitness needs at least one robot's fitness")
    return float(values.mean())
