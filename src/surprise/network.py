"""The actor-predictor network pair and the exact mapping between a flat genome and its weights.

Layout of a genome (one flat float64 vector), in this order, each matrix row-major:

====================  =========================  =================================================
block                 shape                      meaning
====================  =========================  =================================================
actor.hidden          (H_a, R + M + 1)           inputs s(t), a(t-1), bias 1 -> tanh
actor.output          (M, H_a + 1)               hidden, bias 1 -> tanh -> a(t) in [-1, 1]
predictor.hidden      (H_p, R + M + 1)           inputs s(t), a(t), bias 1 -> sigmoid
predictor.self        (H_p,)                     one self-weight per hidden neuron (memory)
predictor.initial     (H_p,)                     hidden state before the first step
predictor.output      (R_free, H_p + 1)          hidden, bias 1 -> sigmoid -> p(t+1) in [0, 1]
====================  =========================  =================================================

R is the number of sensors, M = 2 wheel speeds, R_free the sensors whose prediction is not
predefined. The predictor's hidden layer is h(t) = sigmoid(W [s(t), a(t), 1] + w_self * h(t-1)),
with h(-1) = ``predictor.initial``. If every prediction is predefined, the predictor blocks are
absent and the genome holds the actor only.
"""

from __future__ import annotations

import msgspec
import numpy as np

from surprise.config import ExperimentConfig
from surprise.errors import GenomeError
from surprise.sensors import check_sensor_names

#: Number of actions: left and right wheel speed.
ACTIONS = 2


class NetworkSpec(msgspec.Struct, frozen=True, kw_only=True):
    """Shape of a network pair: all a robot needs besides the genome to run it.

    ``predefined`` maps sensor names to fixed predictions in [0, 1]; ``initial_action`` is the
    value of every a(-1) fed to the actor at the first step of an evaluation.
    """

    sensors: tuple[str, ...]
    actor_hidden: int
    predictor_hidden: int
    predefined: dict[str, float] = msgspec.field(default_factory=dict)
    initial_action: float = 0.0

    def __post_init__(self) -> None:
        check_sensor_names(self.sensors)
        if self.actor_hidden < 1 or self.predictor_hidden < 1:
            raise ValueError("hidden layer sizes must be at least 1")
        for name, value in self.predefined.items():
            if name not in self.sensors:
                raise ValueError(f"predefined prediction for unknown sensor {name!r}")
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"predefined prediction for {name!r} must lie in [0, 1]")


def spec_from_config(config: ExperimentConfig) -> NetworkSpec:
    """The network shape an experiment configuration asks for (predictor default: R + 1)."""
    hidden = config.network.predictor_hidden or len(config.sensors) + 1
    return NetworkSpec(
        sensors=tuple(config.sensors),
        actor_hidden=config.network.actor_hidden,
        predictor_hidden=hidden,
        predefined=dict(config.predefined),
        initial_action=config.network.initial_action,
    )


class GenomeLayout:
    """Where each weight block lives in a flat genome for a given :class:`NetworkSpec`.

    ``blocks`` maps a block name (see the module docstring) to ``(start, shape)``; ``size`` is the
    genome length. ``free`` holds the indices of the sensors whose prediction the network makes,
    ``fixed`` the prediction vector with predefined values filled in (others are 0).
    """

    def __init__(self, spec: NetworkSpec) -> None:
        self.spec = spec
        r, m = len(spec.sensors), ACTIONS
        self.sensors = r
        self.free = np.array(
            [i for i, name in enumerate(spec.sensors) if name not in spec.predefined], dtype=np.intp
        )
        self.fixed = np.array([spec.predefined.get(name, 0.0) for name in spec.sensors])
        self.has_predictor = self.free.size > 0
        shapes: list[tuple[str, tuple[int, ...]]] = [
            ("actor.hidden", (spec.actor_hidden, r + m + 1)),
            ("actor.output", (m, spec.actor_hidden + 1)),
        ]
        if self.has_predictor:
            hp = spec.predictor_hidden
            shapes += [
                ("predictor.hidden", (hp, r + m + 1)),
                ("predictor.self", (hp,)),
                ("predictor.initial", (hp,)),
                ("predictor.output", (self.free.size, hp + 1)),
            ]
        self.blocks: dict[str, tuple[int, tuple[int, ...]]] = {}
        start = 0
        for name, shape in shapes:
            self.blocks[name] = (start, shape)
            start += int(np.prod(shape))
        self.size = start

    def unpack(self, genome: np.ndarray) -> dict[str, np.ndarray]:
        """Views of ``genome`` per block; raises :class:`GenomeError` if it does not fit."""
        genome = np.asarray(genome, dtype=np.float64)
        if genome.shape != (self.size,):
            raise GenomeError(f"genome has shape {genome.shape}, the layout needs ({self.size},)")
        if not np.all(np.isfinite(genome)):
            raise GenomeError("genome holds non-finite values")
        return {
            name: genome[start : start + int(np.prod(shape))].reshape(shape)
            for name, (start, shape) in self.blocks.items()
        }


def _sigmoid(x: np.ndarray) -> np.ndarray:
    # The tanh form is exact and never overflows, unlike 1 / (1 + exp(-x)) for large |x|.
    return 0.5 * (np.tanh(0.5 * x) + 1.0)


class NetworkPair:
    """One genome's actor and predictor, run for a batch of ``robots`` at once.

    Each robot has its own previous action and predictor hidden state. Call :meth:`step` once per
    control step with the sensor readings s(t); it returns the actions a(t) and the predictions
    p(t+1). Arrays are shaped ``(robots, R)`` and ``(robots, 2)``; with 1-D input (one robot) the
    results are 1-D too. :meth:`reset` starts a new evaluation.
    """

    def __init__(self, spec: NetworkSpec, genome: np.ndarray, robots: int = 1) -> None:
        self.layout = GenomeLayout(spec)
        self.robots = robots
        w = self.layout.unpack(genome)
        r = self.layout.sensors
        # The 1-D path multiplies whole rows with one input vector [s, a, 1] (fewest numpy calls
        # per step: it runs at 10 Hz on a Pi and a million times in a simulated experiment); the
        # batched path splits the input weights by source so that it needs no concatenation.
        ah = w["actor.hidden"]
        self._a_in = ah.copy()
        self._a_s, self._a_a, self._a_b = ah[:, :r].T.copy(), ah[:, r:-1].T.copy(), ah[:, -1].copy()
        ao = w["actor.output"]
        self._a_out, self._a_ob = ao[:, :-1].copy(), ao[:, -1].copy()
        self._x = np.ones(r + ACTIONS + 1)  # the 1-D path's input buffer; the bias stays 1
        self._r = r
        self._predefined = self.layout.free.size < r
        if self.layout.has_predictor:
            ph = w["predictor.hidden"]
            self._p_in = ph.copy()
            self._p_s, self._p_a, self._p_b = (
                ph[:, :r].T.copy(),
                ph[:, r:-1].T.copy(),
                ph[:, -1].copy(),
            )
            self._p_self = w["predictor.self"].copy()
            self._p_init = w["predictor.initial"].copy()
            po = w["predictor.output"]
            self._p_out, self._p_ob = po[:, :-1].copy(), po[:, -1].copy()
        else:
            self._p_in = None
        self.previous_action = np.empty((robots, ACTIONS))
        self._previous0 = self.previous_action[0]  # views for the 1-D path, updated in place
        if self.layout.has_predictor:
            self.hidden = np.empty((robots, spec.predictor_hidden))
            self._hidden0 = self.hidden[0]
            self._z = np.empty(spec.predictor_hidden)
        self.reset()

    def reset(self) -> None:
        """Start an evaluation: a(-1) = ``initial_action``, hidden state = the learned one."""
        # In place: the 1-D path keeps views of row 0.
        self.previous_action[:] = self.layout.spec.initial_action
        if self.layout.has_predictor:
            self.hidden[:] = self._p_init

    def act(self, sensors: np.ndarray) -> np.ndarray:
        """a(t) from s(t) and a(t-1) for a batch; remembers a(t) for the next step."""
        hidden = np.tanh(sensors @ self._a_s + self.previous_action @ self._a_a + self._a_b)
        action = np.tanh(hidden @ self._a_out.T + self._a_ob)
        self.previous_action[:] = action
        return action

    def predict(self, sensors: np.ndarray, action: np.ndarray) -> np.ndarray:
        """p(t+1) from s(t) and a(t) for a batch; advances the predictor's hidden state."""
        prediction = np.empty((sensors.shape[0], self.layout.sensors))
        prediction[:] = self.layout.fixed
        if not self.layout.has_predictor:
            return prediction
        self.hidden[:] = _sigmoid(
            sensors @ self._p_s + action @ self._p_a + self._p_b + self._p_self * self.hidden
        )
        prediction[:, self.layout.free] = _sigmoid(self.hidden @ self._p_out.T + self._p_ob)
        return prediction

    def _step_one(self, sensors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, r, previous = self._x, self._r, self._previous0
        x[:r] = sensors
        x[r:-1] = previous
        action = np.tanh(self._a_out @ np.tanh(self._a_in @ x) + self._a_ob)
        previous[:] = action
        if self._p_in is None:
            return action, self.layout.fixed.copy()
        x[r:-1] = action
        hidden = self._hidden0
        hidden *= self._p_self
        hidden += np.matmul(self._p_in, x, out=self._z)
        # sigmoid(h) = (tanh(h / 2) + 1) / 2, in place
        hidden *= 0.5
        np.tanh(hidden, out=hidden)
        hidden += 1.0
        hidden *= 0.5
        out = self._p_out @ hidden
        out += self._p_ob
        out *= 0.5
        np.tanh(out, out=out)
        out += 1.0
        out *= 0.5
        if self._predefined:
            prediction = self.layout.fixed.copy()
            prediction[self.layout.free] = out
            return action, prediction
        return action, out

    def step(self, sensors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One control step: ``(a(t), p(t+1))`` for the readings ``s(t)``."""
        if sensors.ndim == 1 and self.robots == 1 and sensors.shape[0] == self._r:
            return self._step_one(sensors)
        batch = sensors.reshape(1, -1) if sensors.ndim == 1 else sensors
        if batch.shape != (self.robots, self.layout.sensors):
            raise ValueError(
                f"sensors have shape {sensors.shape}, expected ({self.robots}, "
                f"{self.layout.sensors}) or ({self.layout.sensors},) for one robot"
            )
        action = self.act(batch)
        prediction = self.predict(batch, action)
        return (action[0], prediction[0]) if sensors.ndim == 1 else (action, prediction)
