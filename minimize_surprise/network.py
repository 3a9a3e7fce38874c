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

from collections.abc import Sequence
from typing import NamedTuple

import msgspec
import numpy as np

from minimize_surprise.activation import sigmoid, tanh
from minimize_surprise.config import ExperimentConfig
from minimize_surprise.errors import GenomeError
from minimize_surprise.jit import kernel
from minimize_surprise.sensors import check_sensor_names

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


@kernel
def network_step(
    a_in: np.ndarray,
    a_out: np.ndarray,
    p_in: np.ndarray,
    p_self: np.ndarray,
    p_out: np.ndarray,
    free: np.ndarray,
    fixed: np.ndarray,
    sensors: np.ndarray,
    previous: np.ndarray,
    hidden: np.ndarray,
    work: np.ndarray,
    action: np.ndarray,
    prediction: np.ndarray,
) -> None:
    """One control step of one robot's network pair: ``action`` = a(t), ``prediction`` = p(t+1).

    The weights are the genome's blocks (see the module docstring; ``p_in`` has no rows when the
    predictor is dropped). ``previous`` holds a(t-1) and becomes a(t); ``hidden`` is the
    predictor's state h(t-1) and becomes h(t). ``work`` is scratch space of at least
    R + M + 1 + H_a values. ``tanh`` and ``sigmoid`` are :mod:`minimize_surprise.activation`'s.
    """
    r = sensors.shape[0]
    inputs = r + 3
    ha = a_in.shape[0]
    for i in range(r):
        work[i] = sensors[i]
    work[r] = previous[0]
    work[r + 1] = previous[1]
    work[r + 2] = 1.0
    # actor: hidden tanh layer into work[inputs:inputs + ha], then two tanh outputs
    for j in range(ha):
        z = 0.0
        for k in range(inputs):
            z += a_in[j, k] * work[k]
        work[inputs + j] = tanh(z)
    for m in range(2):
        z = a_out[m, ha]
        for j in range(ha):
            z += a_out[m, j] * work[inputs + j]
        action[m] = tanh(z)
    previous[0] = action[0]
    previous[1] = action[1]
    for i in range(r):
        prediction[i] = fixed[i]
    hp = p_in.shape[0]
    if hp == 0:
        return
    # predictor: inputs s(t), a(t), 1; each hidden neuron also feeds back to itself
    work[r] = action[0]
    work[r + 1] = action[1]
    for j in range(hp):
        z = p_self[j] * hidden[j]
        for k in range(inputs):
            z += p_in[j, k] * work[k]
        hidden[j] = sigmoid(z)
    for o in range(free.shape[0]):
        z = p_out[o, hp]
        for j in range(hp):
            z += p_out[o, j] * hidden[j]
        prediction[free[o]] = sigmoid(z)


@kernel
def network_step_lanes(
    a_in: np.ndarray,
    a_out: np.ndarray,
    p_in: np.ndarray,
    p_self: np.ndarray,
    p_out: np.ndarray,
    free: np.ndarray,
    fixed: np.ndarray,
    work: np.ndarray,
    previous: np.ndarray,
    hidden: np.ndarray,
    acc: np.ndarray,
    action: np.ndarray,
    prediction: np.ndarray,
) -> None:
    """:func:`network_step` for L robots at once, each robot a lane of every array, each lane
    with weights of its own (robots of several runs, each run's genome; see
    :func:`lane_weights`): every sum adds the same products in the same order as
    :func:`network_step`, so the results are the same to the last bit, but the robots are
    innermost, where the compiler runs several at once (vector instructions).

    The weights are :class:`LaneWeights`' blocks, lanes last; blocks of a single lane are shared
    by every lane (one genome: a broadcast, cheaper than a weight per lane). ``work``
    (R + 3 + H_a, L): rows 0..R-1 hold the robots' readings s(t) on entry, the rest is scratch;
    ``previous`` (2, L) a(t-1), becoming a(t); ``hidden`` (H_p, L) h(t-1), becoming h(t);
    ``acc`` (at least max(H_a, H_p, R, 2), L) scratch; ``action`` (2, L) a(t); ``prediction``
    (R, L) p(t+1).
    ``free`` and ``fixed`` are the same for every lane (one network shape).
    """
    # Each layer's sums run input by input over all its units at once (``acc``, a row per
    # unit): consecutive additions go to different sums, so none waits for the one before, which
    # a unit-by-unit loop does through memory at every input (docs/simulation.md, "Figures
    # behind the code's choices").
    r = prediction.shape[0]
    n = work.shape[1]
    inputs = r + 3
    ha = a_in.shape[0]
    for i in range(n):
        work[r, i] = previous[0, i]
        work[r + 1, i] = previous[1, i]
        work[r + 2, i] = 1.0
    for j in range(ha):
        for i in range(n):
            acc[j, i] = 0.0
    _add_products(acc, a_in, work, 0, inputs)
    for j in range(ha):
        for i in range(n):
            work[inputs + j, i] = tanh(acc[j, i])
    _set_column(acc, a_out, ha)
    _add_products(acc, a_out, work, inputs, ha)
    for m in range(2):
        for i in range(n):
            a = tanh(acc[m, i])
            action[m, i] = a
            previous[m, i] = a
    for k in range(r):
        for i in range(n):
            prediction[k, i] = fixed[k]
    hp = p_in.shape[0]
    if hp == 0:
        return
    for i in range(n):
        work[r, i] = action[0, i]
        work[r + 1, i] = action[1, i]
    for j in range(hp):
        if p_self.shape[1] == 1:
            w = p_self[j, 0]
            for i in range(n):
                acc[j, i] = w * hidden[j, i]
        else:
            for i in range(n):
                acc[j, i] = p_self[j, i] * hidden[j, i]
    _add_products(acc, p_in, work, 0, inputs)
    for j in range(hp):
        for i in range(n):
            hidden[j, i] = sigmoid(acc[j, i])
    _set_column(acc, p_out, hp)
    _add_products(acc, p_out, hidden, 0, hp)
    for o in range(free.shape[0]):
        row = free[o]
        for i in range(n):
            prediction[row, i] = sigmoid(acc[o, i])


@kernel(inline=True)
def _set_column(acc: np.ndarray, weights: np.ndarray, k: int) -> None:
    # acc[j, i] = weights[j, k, i] for every unit j and lane i (a layer's biases); one lane of
    # weights: the same in all.
    shared = weights.shape[2] == 1
    for j in range(weights.shape[0]):
        if shared:
            w = weights[j, k, 0]
            for i in range(acc.shape[1]):
                acc[j, i] = w
        else:
            for i in range(acc.shape[1]):
                acc[j, i] = weights[j, k, i]


@kernel(inline=True)
def _add_products(
    acc: np.ndarray, weights: np.ndarray, x: np.ndarray, first: int, inputs: int
) -> None:
    # acc[j, i] += weights[j, k, i] * x[first + k, i] for k ascending from 0, for every unit j
    # and lane i; one lane of weights: the same in all (a broadcast, cheaper than a weight per
    # lane). Called once per layer: a call passing arrays costs reference counts, too many per
    # product.
    units, lanes = weights.shape[0], acc.shape[1]
    if weights.shape[2] == 1:
        for k in range(inputs):
            row = first + k
            for j in range(units):
                w = weights[j, k, 0]
                for i in range(lanes):
                    acc[j, i] += w * x[row, i]
        return
    for k in range(inputs):
        row = first + k
        for j in range(units):
            for i in range(lanes):
                acc[j, i] += weights[j, k, i] * x[row, i]


@kernel
def network_step_batch(
    a_in: np.ndarray,
    a_out: np.ndarray,
    p_in: np.ndarray,
    p_self: np.ndarray,
    p_out: np.ndarray,
    free: np.ndarray,
    fixed: np.ndarray,
    sensors: np.ndarray,
    previous: np.ndarray,
    hidden: np.ndarray,
    work: np.ndarray,
    action: np.ndarray,
    prediction: np.ndarray,
) -> None:
    """:func:`network_step` for every row of ``sensors`` (robots sharing one genome)."""
    for i in range(sensors.shape[0]):
        network_step(
            a_in, a_out, p_in, p_self, p_out, free, fixed, sensors[i], previous[i], hidden[i],
            work, action[i], prediction[i],
        )  # fmt: skip


class NetworkPair:
    """One genome's actor and predictor, run for a batch of ``robots`` at once.

    Each robot has its own previous action and predictor hidden state. Call :meth:`step` once per
    control step with the sensor readings s(t); it returns the actions a(t) and the predictions
    p(t+1). Arrays are shaped ``(robots, R)`` and ``(robots, 2)``; with 1-D input (one robot) the
    results are 1-D too. :meth:`reset` starts a new evaluation. Every step runs
    :func:`network_step`, the kernel the simulator's engine runs too.
    """

    def __init__(self, spec: NetworkSpec, genome: np.ndarray, robots: int = 1) -> None:
        self.layout = GenomeLayout(spec)
        self.robots = robots
        self.weights = network_weights(self.layout, genome)
        r = self.layout.sensors
        self._r = r
        self.previous_action = np.empty((robots, ACTIONS))
        self.hidden = np.empty((robots, self.weights.p_in.shape[0]))
        self._work = np.empty(r + ACTIONS + 1 + spec.actor_hidden)
        self._action = np.empty((robots, ACTIONS))
        self._prediction = np.empty((robots, r))
        self.reset()

    def reset(self) -> None:
        """Start an evaluation: a(-1) = ``initial_action``, hidden state = the learned one."""
        self.previous_action[:] = self.layout.spec.initial_action
        self.hidden[:] = self.weights.p_init

    def step(self, sensors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One control step: ``(a(t), p(t+1))`` for the readings ``s(t)`` (fresh arrays)."""
        one = sensors.ndim == 1
        batch = sensors.reshape(1, -1) if one else sensors
        if batch.shape != (self.robots, self._r):
            raise ValueError(
                f"sensors have shape {sensors.shape}, expected ({self.robots}, "
                f"{self._r}) or ({self._r},) for one robot"
            )
        batch = np.ascontiguousarray(batch, dtype=np.float64)
        action, prediction = self._action, self._prediction
        if one:
            network_step(
                *self.weights[:7], batch[0], self.previous_action[0], self.hidden[0], self._work,
                action[0], prediction[0],
            )  # fmt: skip
        else:
            network_step_batch(
                *self.weights[:7], batch, self.previous_action, self.hidden, self._work, action,
                prediction,
            )  # fmt: skip
        if one:
            return action[0].copy(), prediction[0].copy()
        return action.copy(), prediction.copy()


class Weights(NamedTuple):
    """The weights of a genome as the kernels take them (a tuple: the first seven are
    :func:`network_step`'s first arguments, in order); ``p_*`` have no rows when the predictor is
    dropped."""

    a_in: np.ndarray  # actor.hidden
    a_out: np.ndarray  # actor.output
    p_in: np.ndarray  # predictor.hidden
    p_self: np.ndarray  # predictor.self
    p_out: np.ndarray  # predictor.output
    free: np.ndarray  # the sensors whose prediction the network makes (int64)
    fixed: np.ndarray  # the prediction vector with the predefined values filled in
    p_init: np.ndarray  # predictor.initial


def network_weights(layout: GenomeLayout, genome: np.ndarray) -> Weights:
    """Contiguous copies of ``genome``'s blocks for :func:`network_step` (see :class:`Weights`).

    Raises :class:`GenomeError` if the genome does not fit the layout.
    """
    w = layout.unpack(genome)
    r = layout.sensors
    if layout.has_predictor:
        p_in = np.ascontiguousarray(w["predictor.hidden"])
        p_self = w["predictor.self"].copy()
        p_out = np.ascontiguousarray(w["predictor.output"])
        p_init = w["predictor.initial"].copy()
    else:
        p_in = np.zeros((0, r + ACTIONS + 1))
        p_self = np.zeros(0)
        p_out = np.zeros((0, 1))
        p_init = np.zeros(0)
    return Weights(
        np.ascontiguousarray(w["actor.hidden"]),
        np.ascontiguousarray(w["actor.output"]),
        p_in,
        p_self,
        p_out,
        layout.free.astype(np.int64),
        layout.fixed.astype(np.float64),
        p_init,
    )


class LaneWeights(NamedTuple):
    """Several genomes' weights as :func:`network_step_lanes` takes them: each block of
    :class:`Weights` with a last axis of lanes, a lane per robot (see :func:`lane_weights`)."""

    a_in: np.ndarray  # (H_a, R + 3, L)
    a_out: np.ndarray  # (2, H_a + 1, L)
    p_in: np.ndarray  # (H_p, R + 3, L)
    p_self: np.ndarray  # (H_p, L)
    p_out: np.ndarray  # (R_free, H_p + 1, L)
    free: np.ndarray
    fixed: np.ndarray
    p_init: np.ndarray  # (H_p, L)


def lane_weights(weights: Sequence[Weights], robots: int, lanes: int) -> LaneWeights:
    """The lanes of ``len(weights)`` runs of ``robots`` robots each, run by run: genome ``g``'s
    weights in lanes ``g * robots`` to ``(g + 1) * robots - 1``, zeros in the lanes beyond the
    last run's (up to ``lanes``, a whole number of vectors). Every genome has the same shape. One
    genome's weight blocks have a single lane, which every lane shares."""
    first = weights[0]
    if lanes < len(weights) * robots:
        need = len(weights) * robots
        raise ValueError(f"{len(weights)} runs of {robots} robots need {need} lanes, not {lanes}")

    def block(name: str, width: int) -> np.ndarray:
        shape = getattr(first, name).shape
        out = np.zeros((*shape, width))
        if width == 1:
            out[..., 0] = getattr(first, name)
            return out
        for g, w in enumerate(weights):
            value = getattr(w, name)
            if value.shape != shape:
                raise ValueError(f"genome {g}'s {name} has shape {value.shape}, not {shape}")
            out[..., g * robots : (g + 1) * robots] = value[..., None]
        return out

    width = 1 if len(weights) == 1 else lanes
    p_init = block("p_init", lanes) if width > 1 else np.repeat(first.p_init[:, None], lanes, 1)
    return LaneWeights(
        a_in=block("a_in", width),
        a_out=block("a_out", width),
        p_in=block("p_in", width),
        p_self=block("p_self", width),
        p_out=block("p_out", width),
        free=first.free,
        fixed=first.fixed,
        p_init=p_init,
    )
