"""The grid world's predictor on all agents of a genome's runs at once (:mod:`gridworld.runs`).

Every lane (an agent of one of the runs) keeps its hidden units as a row of
:data:`gridworld.simd.UNITS` float32, the units beyond H_p staying 0. Their input sums are
looked up: per genome, a table holds for every pattern of the input bits (2^15 for 14 sensors) a
row of every hidden unit's sum over all inputs (:func:`input_sums`), each the code's float32
additions in input order, so its sums bit for bit. A step adds the self-loops and takes the tanh,
then reads the outputs by sign, a group of lanes at a time in explicit vector code
(:func:`gridworld.simd.step_lanes`).

The outputs' sums there are estimated with fused multiply-adds, and an estimate's sign is taken
only where it lies farther from zero than the estimate's error can reach (:data:`OUTPUT_MARGIN`).
For a lane with a sum within that margin, every output is summed again with the code's additions
in order, which then decide. So the predictions are the ones the code's
sums give, bit for bit. Predictions are bits of a ``uint32`` per lane, sensor k at bit k; the
lanes run to a multiple of :data:`LANE_ALIGN` (the lanes beyond the agents compute on input 0 and
are never read).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from gridworld.simd import GROUP, TERMS, UNITS, read_lanes, row_add, step_lanes
from minimize_surprise.gridnet import GridNetworks, c_activation, c_negative
from minimize_surprise.jit import kernel

__all__ = [
    "LANE_ALIGN",
    "OUTPUT_MARGIN",
    "Predictor",
    "input_sums",
    "make_predictor",
    "predict",
    "predict_outputs",
]

#: The predictor's lanes are padded to a multiple of this (the lanes one vector call steps).
LANE_ALIGN = GROUP

#: An output sum of at most 14 terms estimated with fused multiply-adds in any order lies within
#: 2 * 14 * 2^-24 / (1 - 14 * 2^-24) (1.7e-6) times the sum of its terms' magnitudes of the
#: code's sum (Higham's bound for both, the hidden units within [-1, 1] up to rounding); the
#: estimate's sign is taken where it is farther from zero than this share of the output's
#: absolute weights (plus 1e-9: the code's tanh reads sums within 1e-10 below zero itself).
OUTPUT_MARGIN = np.float32(3e-6)


class Predictor(NamedTuple):
    """Genome ``g``'s predictor as the prediction steps take it (:func:`make_predictor`).

    ``table`` (2^I, :data:`UNITS`): the hidden units' input sums by input bits; ``self_loop``
    (:data:`UNITS`): the units' self-loops; ``weights`` (:data:`UNITS`, :data:`UNITS`): unit j to
    sensor k at [j, k], 0 for a sensor without an output; ``margin`` (:data:`UNITS`): how near
    zero sensor k's estimated sum is summed again (-1 for a sensor without an output); ``keep``:
    the predicted sensors as bits; ``first``: the fixed predictions as bits (those of the first
    step; never a predicted sensor's: ``keep & first`` is 0, which the prediction bits rely on);
    ``exact``: the code's tanh in the hidden units.
    """

    table: np.ndarray
    self_loop: np.ndarray
    weights: np.ndarray
    margin: np.ndarray
    keep: np.uint32
    first: np.uint32
    exact: bool


#: Inputs whose sums :func:`input_sums` builds level by level; the rest continue each row.
LOW_INPUTS = 10


@kernel
def input_sums(u: np.ndarray, w: np.ndarray, g: int, bits: int, out: np.ndarray) -> None:
    """Input-layer sums of genome ``g`` over its first ``bits`` inputs for every pattern of their
    bits, by pattern: ``out[k, j]`` = u[g, bit_0(k), 0] * w[g, j, 0] + u[g, bit_1(k), 1] *
    w[g, j, 1] + ... for hidden unit j, in float32 and in input order as the code adds them
    (``u``: (G, 2, I), ``w``: (G, H, I), ``out``: (2^bits, :data:`UNITS`); units from H on are 0).

    The sums over the first :data:`LOW_INPUTS` inputs are built one input at a time, each level
    from the one before, as :func:`gridworld.kernels.prefix_sums` does by unit; every row then
    adds the remaining inputs' terms in order, one vector addition each
    (:func:`gridworld.simd.row_add`): the same operations, so the same sums, and each row of the
    (2 MB) table is written once instead of at every level. The blocks of rows that share the
    remaining inputs' bits are done from the last to the first, so the first block's sums are
    read before they are overwritten.
    """
    hp = w.shape[1]
    terms = np.zeros((2 * max(bits, 1), UNITS), dtype=np.float32)  # input i, bit v: row 2 i + v
    for i in range(bits):
        for j in range(hp):
            terms[2 * i, j] = u[g, 0, i] * w[g, j, i]
            terms[2 * i + 1, j] = u[g, 1, i] * w[g, j, i]
    low = min(bits, LOW_INPUTS)
    for j in range(UNITS):
        out[0, j] = 0.0
    for i in range(low):
        half = 1 << i
        for k in range(half):
            for j in range(UNITS):
                out[k + half, j] = out[k, j] + terms[2 * i + 1, j]
                out[k, j] = out[k, j] + terms[2 * i, j]
    if bits == low:  # no inputs left to continue the rows with
        return
    block = 1 << low
    for high in range((1 << (bits - low)) - 1, -1, -1):
        start = high * block  # bit i - low of high is input i's
        for k in range(block):
            row_add(out, start + k, k, terms, 2 * low + (high & 1))
            for i in range(low + 1, bits):
                row_add(out, start + k, start + k, terms, 2 * i + ((high >> (i - low)) & 1))


@kernel
def make_predictor(nets: GridNetworks, g: int, exact: bool, table: np.ndarray) -> Predictor:
    """Genome g's :class:`Predictor`, its input sums built into ``table`` ((2^I, :data:`UNITS`),
    made once per batch: 2 MB for 14 sensors, which a fresh allocation per genome would fault in
    again). Refuses a predictor of more than :data:`gridworld.simd.TERMS` hidden units or
    sensors (no sensor model has one)."""
    p_u, p_hidden, p_out, fixed, outputs = (
        nets.p_u,
        nets.p_hidden,
        nets.p_out,
        nets.fixed,
        nets.outputs,
    )
    inputs, hp, o = p_u.shape[2], p_hidden.shape[1], p_out.shape[1]
    if hp > TERMS or fixed.shape[0] > TERMS:
        raise ValueError("the predictor has more hidden units or sensors than its vectors hold")
    if table.shape[0] != 1 << inputs or table.shape[1] != UNITS:
        raise ValueError("the predictor's table must have a row of 16 per input pattern")
    input_sums(p_u, p_hidden, g, inputs, table)
    first = np.int64(0)
    for k in range(fixed.shape[0]):
        first |= np.int64(fixed[k]) << k
    keep = np.int64(0)
    weights = np.zeros((UNITS, UNITS), dtype=np.float32)
    margin = np.full(UNITS, -1.0, dtype=np.float32)
    for q in range(o):
        k = outputs[q]
        keep |= np.int64(1) << k
        total = np.float32(0.0)
        for j in range(hp):
            weights[j, k] = p_out[g, q, j]
            total += abs(p_out[g, q, j])
        margin[k] = OUTPUT_MARGIN * total + np.float32(1e-9)
    self_loop = np.zeros(UNITS, dtype=np.float32)
    for j in range(hp):
        self_loop[j] = nets.p_self[g, j]
    return Predictor(table, self_loop, weights, margin, np.uint32(keep), np.uint32(first), exact)


@kernel
def _settle(
    predictor: Predictor, hidden: np.ndarray, a: int, unsure: int, pmask: np.ndarray
) -> None:
    # The predictions of the group's lanes flagged in `unsure` from the code's output sums: the
    # terms added in order from 0, the code's tanh deciding right below 0. Summed over all
    # TERMS units: those beyond H_p are 0 with weights 0, and adding +0 changes no sign reading
    # (an exact -0 becomes +0, and both read as not negative).
    weights, keep = predictor.weights, predictor.keep
    for lane in range(a, a + GROUP):
        if not (unsure >> (lane - a)) & 1:
            continue
        bits = pmask[lane]
        for k in range(TERMS):
            bit = np.uint32(1) << np.uint32(k)
            if keep & bit:
                z = np.float32(0.0)
                for j in range(TERMS):
                    z = z + hidden[lane, j] * weights[j, k]
                bits = (bits & ~bit) | (np.uint32(0) if c_negative(z) else bit)
        pmask[lane] = bits


@kernel
def _check_lanes(lanes: int, hidden: np.ndarray, pmask: np.ndarray) -> None:
    # The vector code reads and writes whole groups of rows unchecked: the shapes are checked here
    if lanes % GROUP != 0 or hidden.shape[0] < lanes or hidden.shape[1] != UNITS:
        raise ValueError("the hidden states must be (lanes, 16), lanes a multiple of 16")
    if pmask.shape[0] < lanes:
        raise ValueError("the predictions need a bit mask per lane")


@kernel
def predict_outputs(predictor: Predictor, hidden: np.ndarray, pmask: np.ndarray) -> None:
    """The predictions of every lane (``pmask``, bit k: sensor k, over the fixed ones) from its
    hidden states (``hidden``: (lanes, :data:`UNITS`), lanes a multiple of :data:`LANE_ALIGN`)."""
    weights, margin, keep, first = (
        predictor.weights,
        predictor.margin,
        predictor.keep,
        predictor.first,
    )
    _check_lanes(hidden.shape[0], hidden, pmask)
    for a in range(0, hidden.shape[0], GROUP):
        unsure = read_lanes(hidden, a, weights, margin, pmask, keep, first)
        if unsure != 0:  # a sum too near zero for its estimate's sign: the code's sums decide
            _settle(predictor, hidden, a, unsure, pmask)


@kernel
def predict(predictor: Predictor, pkey: np.ndarray, hidden: np.ndarray, pmask: np.ndarray) -> None:
    """One step of the predictor on all lanes: the hidden states (``hidden``: (lanes,
    :data:`UNITS`)) from inputs ``pkey``, then the next step's predictions into ``pmask``
    (:func:`predict_outputs`)."""
    table, self_loop, weights, margin, keep, first = predictor[:6]
    _check_lanes(pkey.shape[0], hidden, pmask)
    if predictor.exact:
        for lane in range(pkey.shape[0]):
            sums = table[pkey[lane]]
            for j in range(UNITS):
                hidden[lane, j] = c_activation(sums[j] + hidden[lane, j] * self_loop[j])
        predict_outputs(predictor, hidden, pmask)
        return
    for a in range(0, pkey.shape[0], GROUP):
        unsure = step_lanes(table, pkey, hidden, a, self_loop, weights, margin, pmask, keep,
                            first)  # fmt: skip
        if unsure != 0:
            _settle(predictor, hidden, a, unsure, pmask)
