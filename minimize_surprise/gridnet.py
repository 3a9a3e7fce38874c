"""The grid world's actor-predictor pair and its genome layout (paper Sec. III; the authors' code).

Both networks take the agent's R binary sensor values and one bit of action (a0 = 0 move forward,
1 turn). Each input x_i passes its own *input unit* u_i = tanh(w_i x_i - theta_i) first; the hidden
and output layers have no biases. The actor's two outputs are read by sign: o0 < 0 moves, else
turns; o1 < 0 turns left (+90 degrees), else right. Its a0 is fed back as the next step's action
input (a0(-1) = 0); the turn direction is not. The predictor gets this step's a0 and has one
self-loop per hidden unit (h(-1) = 0); each output predicts one sensor: < 0 means 0, else 1.
tanh is the code's ``2 / (1 + exp(-2x)) - 1``, and weights and sums are float32 as in the code.

Layout of a genome (one flat float64 vector), in this order, each matrix row-major:

======================  ================  ======================================================
block                   shape             meaning
======================  ================  ======================================================
actor.input             (I, 2)            per input i: weight w_i, threshold theta_i
actor.hidden            (H_a, I)          input unit i -> hidden j (tanh, no bias)
actor.output            (2, H_a)          hidden j -> output k (k = 0 move/turn, 1 direction)
predictor.input         (I, 2)            per input i: weight w_i, threshold theta_i
predictor.hidden        (H_p, I + 1)      input unit i -> hidden j; column I: self-loop v_j
predictor.output        (O, H_p)          hidden j -> output k, the prediction of sensor
                                          ``outputs[k]``
======================  ================  ======================================================

I = R + 1 inputs (the R sensors in the sensor model's order, then a0). Sizes by sensor model:
R = 14: H_a = 8, H_p = 14; R = 8: 6 and 8; R = 6: 4 and 6. O = R unless predictions are fixed.
Each block is, entry for entry, the used prefix of the code's layer array of the same network
(layer 0 = input, 1 = hidden, 2 = output): the code keeps 3 x CONNECTIONS floats per network
and initialises and mutates the unused tail too, which only consumes random numbers; it has no
counterpart here (616 genes for R = 14 instead of 2 x 3 x 224).

Fixed predictions (paper Sec. IV-F, :data:`TARGETS`): a target fixes each sensor's prediction to
0 or 1. ``NAME`` fixes all of them: there is no predictor and the genome is the actor blocks only.
``NAME-partial`` fixes the sensors the target sets to 1 and lets the predictor learn the others
(O = R minus those, in sensor order, H_p = O + 2): for ``line-partial`` with 14 sensors this is
the code's MAN LINE network (hidden 12, outputs for sensors 1, 2, 4, 5, 6, 7, 9, 10, 12, 13). A
target that fixes no sensor or every sensor to 1 cannot be partial. The first step's scored
predictions are the fixed values (0 for learned sensors). ``actor_only`` (novelty search) also
drops the predictor; predictions are then all 0 and mean nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, SupportsFloat

import numpy as np

from minimize_surprise.errors import GenomeError
from minimize_surprise.jit import kernel

__all__ = [
    "SENSOR_MODELS",
    "TARGETS",
    "GridGenomeLayout",
    "GridNetSpec",
    "GridNetworks",
    "activation",
    "actor_reference",
    "grid_networks",
    "predictor_reference",
]

#: Hidden sizes (actor, predictor) by number of sensors, as the code's headers set them.
SENSOR_MODELS: dict[int, tuple[int, int]] = {14: (8, 14), 8: (6, 8), 6: (4, 6)}

#: Sensors a target predicts as occupied, per sensor model; every other sensor is predicted 0.
TARGETS: dict[str, dict[int, tuple[int, ...]]] = {
    "line": {14: (0, 3, 8, 11), 6: (0, 3), 8: (0, 5)},
    "pair": {14: (0,), 6: (0,), 8: (0,)},
    "square": {14: (3, 11), 6: (), 8: ()},
    "triangular-lattice": {14: (1, 2, 3, 9, 10, 11), 6: (), 8: ()},
    "aggregation": {14: tuple(range(14)), 6: tuple(range(6)), 8: tuple(range(8))},
    "dispersion": {14: (), 6: (), 8: ()},
}

PARTIAL_SUFFIX = "-partial"


def predefined_names() -> tuple[str, ...]:
    """Every accepted ``predefined`` value: each target, fixed whole or partly."""
    return tuple(TARGETS) + tuple(name + PARTIAL_SUFFIX for name in TARGETS)


@dataclass(frozen=True)
class GridNetSpec:
    """Shape of a grid agent's network pair: ``sensors`` (6, 8 or 14), the fixed predictions
    (``predefined``: a name of :func:`predefined_names` or None) and whether only the actor
    exists (``actor_only``, novelty search). Raises ValueError naming what is wrong."""

    sensors: int = 14
    predefined: str | None = None
    actor_only: bool = False

    def __post_init__(self) -> None:
        if self.sensors not in SENSOR_MODELS:
            raise ValueError(f"sensors must be one of 14, 6, 8, got {self.sensors}")
        if self.predefined is not None:
            if self.predefined not in predefined_names():
                raise ValueError(
                    f"unknown predefined prediction {self.predefined!r}; "
                    f"expected one of {', '.join(predefined_names())}"
                )
            if self.partial:
                target = self.predefined.removesuffix(PARTIAL_SUFFIX)  # == self.target
                ones = TARGETS[target][self.sensors]
                if not 0 < len(ones) < self.sensors:
                    raise ValueError(
                        f"{self.predefined!r} with {self.sensors} sensors fixes "
                        f"{'no' if not ones else 'every'} sensor to 1, so nothing is left to "
                        f"fix partly; use {target!r}"
                    )

    @property
    def partial(self) -> bool:
        """True when some predictions are fixed and the predictor learns the others."""
        return self.predefined is not None and self.predefined.endswith(PARTIAL_SUFFIX)

    @property
    def target(self) -> str | None:
        """The target's name without ``-partial``."""
        if self.predefined is None:
            return None
        return self.predefined.removesuffix(PARTIAL_SUFFIX)

    @property
    def fixed(self) -> np.ndarray:
        """The predictions a run starts with (the fixed values; 0 for learned sensors)."""
        out = np.zeros(self.sensors, dtype=np.int8)
        if self.target is not None:
            out[list(TARGETS[self.target][self.sensors])] = 1
        return out

    @property
    def outputs(self) -> tuple[int, ...]:
        """The sensors the predictor predicts, in output order (empty: no predictor)."""
        if self.actor_only or (self.predefined is not None and not self.partial):
            return ()
        target = self.target
        if target is not None and self.partial:  # partial: a target is named
            ones = set(TARGETS[target][self.sensors])
            return tuple(r for r in range(self.sensors) if r not in ones)
        return tuple(range(self.sensors))

    @property
    def actor_hidden(self) -> int:
        """Hidden units of the actor."""
        return SENSOR_MODELS[self.sensors][0]

    @property
    def predictor_hidden(self) -> int:
        """Hidden units of the predictor (0 when there is none)."""
        outputs = len(self.outputs)
        if outputs == 0:
            return 0
        return outputs + 2 if self.partial else SENSOR_MODELS[self.sensors][1]


class GridGenomeLayout:
    """Where each block of the module docstring lives in a flat genome for ``spec``.

    ``blocks`` maps a block name to ``(start, shape)``; ``size`` is the genome length.
    """

    def __init__(self, spec: GridNetSpec) -> None:
        self.spec = spec
        inputs = spec.sensors + 1
        ha, hp, outputs = spec.actor_hidden, spec.predictor_hidden, len(spec.outputs)
        shapes: list[tuple[str, tuple[int, ...]]] = [
            ("actor.input", (inputs, 2)),
            ("actor.hidden", (ha, inputs)),
            ("actor.output", (2, ha)),
        ]
        if outputs:
            shapes += [
                ("predictor.input", (inputs, 2)),
                ("predictor.hidden", (hp, inputs + 1)),
                ("predictor.output", (outputs, hp)),
            ]
        self.blocks: dict[str, tuple[int, tuple[int, ...]]] = {}
        start = 0
        for name, shape in shapes:
            self.blocks[name] = (start, shape)
            start += math.prod(shape)
        self.size = start

    @property
    def has_predictor(self) -> bool:
        """Whether the genome holds a predictor."""
        return "predictor.input" in self.blocks

    def unpack(self, genome: np.ndarray) -> dict[str, np.ndarray]:
        """Views of ``genome`` per block; raises :class:`GenomeError` if it does not fit."""
        genome = np.asarray(genome, dtype=np.float64)
        if genome.shape != (self.size,):
            raise GenomeError(f"genome has shape {genome.shape}, the layout needs ({self.size},)")
        if not np.all(np.isfinite(genome)):
            raise GenomeError("genome holds non-finite values")
        return {
            name: genome[start : start + math.prod(shape)].reshape(shape)
            for name, (start, shape) in self.blocks.items()
        }


def activation(x: SupportsFloat) -> float:
    """The code's tanh, ``2 / (1 + exp(-2x)) - 1`` in double, returned as float32."""
    return float(np.float32(2.0 / (1.0 + math.exp(-2.0 * float(x))) - 1.0))


@kernel
def c_activation(x: float) -> np.float32:
    """:func:`activation` as a kernel."""
    return np.float32(2.0 / (1.0 + np.exp(-2.0 * x)) - 1.0)


@kernel
def c_negative(x: np.float32) -> bool:
    """Whether the code reads a unit with net input ``x`` as negative (``activation(x) < 0``).

    The sign of x decides, except within 1e-10 below zero where exp(-2x) may round to exactly 1
    and the code's tanh gives 0 (not negative): there the code's formula itself decides.
    """
    if x >= 0.0:
        return False
    if x < -1e-10:
        return True
    return c_activation(x) < 0.0


def _input_units(block: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Binary inputs make every input unit two-valued: u(0) = tanh(-theta), u(1) = tanh(w - theta),
    # each computed as the code does (float32 product and difference, then its tanh).
    w = block[:, 0].astype(np.float32)
    theta = block[:, 1].astype(np.float32)
    u0 = np.array(
        [activation(np.float32(0.0) * wi - ti) for wi, ti in zip(w, theta, strict=True)], np.float32
    )
    u1 = np.array(
        [activation(np.float32(1.0) * wi - ti) for wi, ti in zip(w, theta, strict=True)], np.float32
    )
    return u0, u1


class GridNetworks(NamedTuple):
    """A batch of G genomes as the kernels take them (float32, contiguous, genome first): a
    named tuple, so the compiled kernels take it whole.

    ``a_u`` (G, 2, I): actor input units for input 0 and 1; ``a_hidden`` (G, H_a, I);
    ``a_out`` (G, 2, H_a); ``p_u`` (G, 2, I); ``p_hidden`` (G, H_p, I); ``p_self`` (G, H_p);
    ``p_out`` (G, O, H_p); ``outputs`` (O,) the sensor of each output; ``fixed`` (R,) the first
    step's predictions. Without a predictor the ``p_*`` arrays have H_p = O = 0.
    """

    a_u: np.ndarray
    a_hidden: np.ndarray
    a_out: np.ndarray
    p_u: np.ndarray
    p_hidden: np.ndarray
    p_self: np.ndarray
    p_out: np.ndarray
    outputs: np.ndarray
    fixed: np.ndarray

    @property
    def genomes(self) -> int:
        """Number of genomes G."""
        return self.a_u.shape[0]


def grid_networks(layout: GridGenomeLayout, genomes: np.ndarray) -> GridNetworks:
    """The kernel arrays of ``genomes`` (shape (G, size) or (size,)); :class:`GenomeError` if a
    genome does not fit ``layout``."""
    genomes = np.asarray(genomes, dtype=np.float64)
    if genomes.ndim == 1:
        genomes = genomes[None, :]
    spec = layout.spec
    g, inputs = genomes.shape[0], spec.sensors + 1
    ha, hp, outputs = spec.actor_hidden, spec.predictor_hidden, len(spec.outputs)
    f32 = np.float32
    a_u = np.empty((g, 2, inputs), f32)
    a_hidden = np.empty((g, ha, inputs), f32)
    a_out = np.empty((g, 2, ha), f32)
    p_u = np.zeros((g, 2, inputs), f32)
    p_hidden = np.zeros((g, hp, inputs), f32)
    p_self = np.zeros((g, hp), f32)
    p_out = np.zeros((g, outputs, hp), f32)
    for i, genome in enumerate(genomes):
        w = layout.unpack(genome)
        a_u[i] = _input_units(w["actor.input"])
        a_hidden[i] = w["actor.hidden"]
        a_out[i] = w["actor.output"]
        if outputs:
            p_u[i] = _input_units(w["predictor.input"])
            p_hidden[i] = w["predictor.hidden"][:, :inputs]
            p_self[i] = w["predictor.hidden"][:, inputs]
            p_out[i] = w["predictor.output"]
    return GridNetworks(
        a_u, a_hidden, a_out, p_u, p_hidden, p_self, p_out,
        np.array(spec.outputs, dtype=np.int64), spec.fixed.astype(np.int8),
    )  # fmt: skip


# --- plain-loop references: the code's propagation written out, for tests and documentation ---


def actor_reference(layout: GridGenomeLayout, genome: np.ndarray, inputs) -> tuple[int, int]:
    """The actor's decision for ``inputs`` (R sensor bits, then a0(t-1)) as the code computes it:
    ``(a0, turn)`` with a0 = 0 move / 1 turn and turn = +1 left / -1 right."""
    w = layout.unpack(genome)
    f32 = np.float32
    units = [
        activation(f32(x) * f32(w["actor.input"][i, 0]) - f32(w["actor.input"][i, 1]))
        for i, x in enumerate(inputs)
    ]
    hidden = []
    for j in range(layout.spec.actor_hidden):
        z = f32(0.0)
        for i, u in enumerate(units):
            z = f32(z + f32(f32(u) * f32(w["actor.hidden"][j, i])))
        hidden.append(activation(z))
    out = []
    for k in range(2):
        z = f32(0.0)
        for j, h in enumerate(hidden):
            z = f32(z + f32(f32(h) * f32(w["actor.output"][k, j])))
        out.append(activation(z))
    return (0 if out[0] < 0.0 else 1), (1 if out[1] < 0.0 else -1)


def predictor_reference(
    layout: GridGenomeLayout, genome: np.ndarray, inputs, hidden: list[float]
) -> tuple[list[int], list[float]]:
    """One predictor step as the code computes it: ``inputs`` are R sensor bits then this step's
    a0, ``hidden`` the previous hidden state; returns ``(predictions of all R sensors, new
    hidden state)`` with fixed sensors at their fixed values."""
    spec = layout.spec
    w = layout.unpack(genome)
    f32 = np.float32
    n = spec.sensors + 1
    units = [
        activation(f32(x) * f32(w["predictor.input"][i, 0]) - f32(w["predictor.input"][i, 1]))
        for i, x in enumerate(inputs)
    ]
    new_hidden = []
    for j in range(spec.predictor_hidden):
        z = f32(0.0)
        for i, u in enumerate(units):
            z = f32(z + f32(f32(u) * f32(w["predictor.hidden"][j, i])))
        z = f32(z + f32(f32(hidden[j]) * f32(w["predictor.hidden"][j, n])))
        new_hidden.append(activation(z))
    predictions = [int(v) for v in spec.fixed]
    for k, sensor in enumerate(spec.outputs):
        z = f32(0.0)
        for j, h in enumerate(new_hidden):
            z = f32(z + f32(f32(h) * f32(w["predictor.output"][k, j])))
        predictions[sensor] = 0 if activation(z) < 0.0 else 1
    return predictions, new_hidden
