"""The grid world's predictor on all agents of a genome's runs at once (:mod:`gridworld.runs`).

The hidden units' input sums are looked up: per genome, a table holds the sum over all inputs of
every hidden unit for every pattern of the input bits (:func:`gridworld.kernels.prefix_sums` over
all of them, 2^15 patterns for 14 sensors), each the code's float32 additions in input order, so
its sums bit for bit. A step then gathers one sum per unit and agent and adds the self-loop.

The outputs are read by sign. With more than 8 hidden units every output's sum is written out
term by term in one pass over all lanes: 14 terms, the units beyond H_p being zero with zero
weights, which adds +0 to a sum and so changes no sign reading (an exact -0 becomes +0, and both
read as 0 or more). The terms stay in registers instead of going through memory. That pass
estimates each sum with fused multiply-adds (:func:`gridworld.kernels.mul_add`, half the
arithmetic) and takes its sign where it lies farther from zero than the estimate's error can
reach (:data:`OUTPUT_MARGIN`); a pass with a sum within that margin is done again with the
code's additions, which then decide. Predictions are bits of a ``uint32`` per lane; the lanes
run to a multiple of :data:`LANE_ALIGN`, so the vector loops have no scalar remainder (the
lanes beyond the agents compute on input 0 and are never read).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from gridworld.kernels import mul_add, prefix_sums, tanh_fast
from minimize_surprise.gridnet import GridNetworks, c_activation, c_negative
from minimize_surprise.jit import kernel

__all__ = [
    "LANE_ALIGN",
    "OUTPUT_MARGIN",
    "WIDE",
    "Predictor",
    "Sums",
    "make_predictor",
    "predict_hidden",
    "predict_outputs",
]

#: Hidden units the written-out output sums take; predictors with more than 8 and at most this
#: many use them (fewer units would add too many zero terms).
WIDE = 14

#: The predictor's lanes are padded to a multiple of this (a vector of 16 float32, unrolled).
LANE_ALIGN = 64

#: A written-out output sum estimated with fused multiply-adds in any order lies within
#: 2 * 14 * 2^-24 / (1 - 14 * 2^-24) (1.7e-6) times the sum of its terms' magnitudes of the
#: code's sum (Higham's bound for both, the hidden units within [-1, 1] up to rounding); the
#: estimate's sign is taken where it is farther from zero than this share of the output's
#: absolute weights (plus 1e-9: the code's tanh reads sums within 1e-10 below zero itself).
OUTPUT_MARGIN = np.float32(3e-6)


class Predictor(NamedTuple):
    """Genome ``g``'s predictor as the prediction steps take it: ``self_loop`` (H_p) its hidden
    units' self-loops, ``out`` (O, H_p, or O, :data:`WIDE` zero-padded when ``wide``) its output
    weights, ``margin`` (O) how near zero an output's estimated sum is done again
    (:data:`OUTPUT_MARGIN`), ``outputs`` the sensor of each output, ``table`` (H_p, 2^I) the
    hidden units' input sums by input bits, ``first`` the first
    step's (fixed) predictions as bits, sensor k at bit k, ``exact``: the code's tanh in the
    hidden units."""

    self_loop: np.ndarray
    out: np.ndarray
    margin: np.ndarray
    outputs: np.ndarray
    table: np.ndarray
    first: np.uint32
    exact: bool
    wide: bool


class Sums(NamedTuple):
    """The prediction steps' working space per lane: ``low`` a lane's table column (unsigned, as
    every index of a per-lane loop: a signed index costs a check for negative values that keeps
    the loop from being compiled tightly), ``acc`` ... ``acc4`` the sums of up to four units."""

    low: np.ndarray
    acc: np.ndarray
    acc2: np.ndarray
    acc3: np.ndarray
    acc4: np.ndarray


@kernel
def make_predictor(nets: GridNetworks, g: int, exact: bool, table: np.ndarray) -> Predictor:
    """Genome g's :class:`Predictor`, its input sums built into ``table`` ((H_p, 2^I), made once
    per batch: 1.8 MB for 14 sensors, which a fresh allocation per genome would fault in again)."""
    p_u, p_hidden, p_out, fixed = nets.p_u, nets.p_hidden, nets.p_out, nets.fixed
    inputs, hp, o = p_u.shape[2], p_hidden.shape[1], p_out.shape[1]
    prefix_sums(p_u, p_hidden, g, inputs, table)
    bits = np.int64(0)
    for k in range(fixed.shape[0]):
        bits |= np.int64(fixed[k]) << k
    first = np.uint32(bits)
    wide = 8 < hp <= WIDE
    out = np.zeros((o, WIDE if wide else hp), dtype=np.float32)
    margin = np.empty(o, dtype=np.float32)
    for q in range(o):
        weights = np.float32(0.0)
        for j in range(hp):
            out[q, j] = p_out[g, q, j]
            weights += abs(p_out[g, q, j])
        margin[q] = OUTPUT_MARGIN * weights + np.float32(1e-9)
    self_loop = np.empty(hp, dtype=np.float32)
    for j in range(hp):
        self_loop[j] = nets.p_self[g, j]
    return Predictor(self_loop, out, margin, nets.outputs, table, first, exact, wide)


@kernel
def predict_hidden(predictor: Predictor, pkey: np.ndarray, hidden: np.ndarray, sums: Sums) -> None:
    """The predictor's hidden units on all lanes (``hidden``: (H_p or more, lanes), their state)
    for inputs ``pkey``: each unit's input sum from the table, then its self-loop."""
    p_self, table, exact = predictor.self_loop, predictor.table, predictor.exact
    low, acc = sums.low, sums.acc
    lanes = pkey.shape[0]
    for a in range(lanes):
        low[a] = np.uint32(pkey[a])
    for j in range(table.shape[0]):
        row = table[j]
        # the gather alone vectorises; with the tanh in the same loop it does not
        for a in range(lanes):
            acc[a] = row[low[a]]
        v = p_self[j]
        if exact:
            for a in range(lanes):
                hidden[j, a] = c_activation(acc[a] + hidden[j, a] * v)
        else:
            for a in range(lanes):
                hidden[j, a] = tanh_fast(acc[a] + hidden[j, a] * v)


@kernel(inline=True)
def _wide_sum(
    hidden: np.ndarray, a: np.uint64, w0: np.float32, w1: np.float32, w2: np.float32,
    w3: np.float32, w4: np.float32, w5: np.float32, w6: np.float32, w7: np.float32,
    w8: np.float32, w9: np.float32, w10: np.float32, w11: np.float32, w12: np.float32,
    w13: np.float32,
) -> np.float32:  # fmt: skip
    # One output's net input on lane a, its terms added in order as the code adds them.
    z = np.float32(0.0) + hidden[0, a] * w0
    z = z + hidden[1, a] * w1
    z = z + hidden[2, a] * w2
    z = z + hidden[3, a] * w3
    z = z + hidden[4, a] * w4
    z = z + hidden[5, a] * w5
    z = z + hidden[6, a] * w6
    z = z + hidden[7, a] * w7
    z = z + hidden[8, a] * w8
    z = z + hidden[9, a] * w9
    z = z + hidden[10, a] * w10
    z = z + hidden[11, a] * w11
    z = z + hidden[12, a] * w12
    return z + hidden[13, a] * w13


@kernel(inline=True)
def _wide_estimate(
    hidden: np.ndarray, a: np.uint64, w0: np.float32, w1: np.float32, w2: np.float32,
    w3: np.float32, w4: np.float32, w5: np.float32, w6: np.float32, w7: np.float32,
    w8: np.float32, w9: np.float32, w10: np.float32, w11: np.float32, w12: np.float32,
    w13: np.float32,
) -> np.float32:  # fmt: skip
    # _wide_sum's net input with fused multiply-adds: within OUTPUT_MARGIN of it.
    z = hidden[0, a] * w0
    z = mul_add(hidden[1, a], w1, z)
    z = mul_add(hidden[2, a], w2, z)
    z = mul_add(hidden[3, a], w3, z)
    z = mul_add(hidden[4, a], w4, z)
    z = mul_add(hidden[5, a], w5, z)
    z = mul_add(hidden[6, a], w6, z)
    z = mul_add(hidden[7, a], w7, z)
    z = mul_add(hidden[8, a], w8, z)
    z = mul_add(hidden[9, a], w9, z)
    z = mul_add(hidden[10, a], w10, z)
    z = mul_add(hidden[11, a], w11, z)
    z = mul_add(hidden[12, a], w12, z)
    return mul_add(hidden[13, a], w13, z)


@kernel
def _outputs_wide(
    out: np.ndarray, margin: np.ndarray, outputs: np.ndarray, hidden: np.ndarray, pmask: np.ndarray
) -> None:
    # Two outputs (q, r) in one pass over all lanes, the sums written out and estimated
    # (module docstring): the two share the loads of the hidden units. (Given the Predictor
    # whole, the pass is not vectorised as well.)
    o = out.shape[0]
    lanes = np.uint64(pmask.shape[0])
    zero = np.uint32(0)
    for q in range(0, o, 2):
        r = q + 1 if q + 1 < o else q  # r == q: an odd last output, read twice
        w0, w1, w2, w3, w4 = out[q, 0], out[q, 1], out[q, 2], out[q, 3], out[q, 4]
        w5, w6, w7, w8, w9 = out[q, 5], out[q, 6], out[q, 7], out[q, 8], out[q, 9]
        w10, w11, w12, w13 = out[q, 10], out[q, 11], out[q, 12], out[q, 13]
        v0, v1, v2, v3, v4 = out[r, 0], out[r, 1], out[r, 2], out[r, 3], out[r, 4]
        v5, v6, v7, v8, v9 = out[r, 5], out[r, 6], out[r, 7], out[r, 8], out[r, 9]
        v10, v11, v12, v13 = out[r, 10], out[r, 11], out[r, 12], out[r, 13]
        mq, mr = margin[q], margin[r]
        bq, br = np.uint32(1) << np.uint32(outputs[q]), np.uint32(1) << np.uint32(outputs[r])
        unsure = False
        for a in range(lanes):
            z = _wide_estimate(hidden, a, w0, w1, w2, w3, w4, w5, w6, w7, w8, w9, w10, w11,
                               w12, w13)  # fmt: skip
            y = _wide_estimate(hidden, a, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11,
                               v12, v13)  # fmt: skip
            pmask[a] |= (bq if z >= 0.0 else zero) | (br if y >= 0.0 else zero)
            unsure |= (abs(z) <= mq) | (abs(y) <= mr)
        if unsure:  # a sum too near zero for its estimate's sign: the code's sums decide
            for a in range(lanes):
                z = _wide_sum(hidden, a, w0, w1, w2, w3, w4, w5, w6, w7, w8, w9, w10, w11,
                              w12, w13)  # fmt: skip
                y = _wide_sum(hidden, a, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11,
                              v12, v13)  # fmt: skip
                bits = pmask[a] & ~(bq | br)
                pmask[a] = bits | (zero if c_negative(z) else bq) | (zero if c_negative(y) else br)


@kernel
def _read_outputs(acc: np.ndarray, sensor: int, pmask: np.ndarray) -> None:
    # One output's net inputs to prediction bits of its sensor in pmask.
    bit = np.uint32(1) << np.uint32(sensor)
    zero = np.uint32(0)
    # below -2e-10 in float32 is below -1e-10, where the code's tanh is surely negative
    near = np.float32(-2e-10)
    tiny = False
    for a in range(np.uint64(acc.shape[0])):
        pmask[a] |= bit if acc[a] >= 0.0 else zero
        tiny |= (acc[a] < 0.0) & (acc[a] > near)
    if tiny:  # where the code's tanh may round to 0, let it decide
        for a in range(acc.shape[0]):
            if acc[a] < 0.0 and not c_negative(acc[a]):
                pmask[a] |= bit


@kernel
def predict_outputs(
    predictor: Predictor, hidden: np.ndarray, pmask: np.ndarray, sums: Sums
) -> None:
    """The predictor's outputs on all lanes: the next step's predictions into ``pmask`` (bit k:
    sensor k, over the first step's fixed ones). Written-out sums when ``predictor.wide``, else
    four outputs at a time."""
    p_out, margin, outputs, first = (
        predictor.out,
        predictor.margin,
        predictor.outputs,
        predictor.first,
    )
    acc, acc2, acc3, acc4 = sums.acc, sums.acc2, sums.acc3, sums.acc4
    lanes = pmask.shape[0]
    hp = p_out.shape[1]
    o = outputs.shape[0]
    if o > 0:
        for a in range(lanes):
            pmask[a] = first
    if predictor.wide:
        _outputs_wide(p_out, margin, outputs, hidden, pmask)
        return
    for q in range(0, o, 4):
        qa = min(q + 1, o - 1)
        qb = min(q + 2, o - 1)
        qc = min(q + 3, o - 1)
        for a in range(lanes):
            acc[a] = 0.0
            acc2[a] = 0.0
            acc3[a] = 0.0
            acc4[a] = 0.0
        for j in range(0, hp - 1, 2):
            w, w1 = p_out[q, j], p_out[q, j + 1]
            x, x1 = p_out[qa, j], p_out[qa, j + 1]
            y, y1 = p_out[qb, j], p_out[qb, j + 1]
            z, z1 = p_out[qc, j], p_out[qc, j + 1]
            for a in range(lanes):
                h, h1 = hidden[j, a], hidden[j + 1, a]
                acc[a] = acc[a] + h * w + h1 * w1
                acc2[a] = acc2[a] + h * x + h1 * x1
                acc3[a] = acc3[a] + h * y + h1 * y1
                acc4[a] = acc4[a] + h * z + h1 * z1
        if hp % 2 == 1:
            w, x = p_out[q, hp - 1], p_out[qa, hp - 1]
            y, z = p_out[qb, hp - 1], p_out[qc, hp - 1]
            for a in range(lanes):
                h = hidden[hp - 1, a]
                acc[a] += h * w
                acc2[a] += h * x
                acc3[a] += h * y
                acc4[a] += h * z
        _read_outputs(acc, outputs[q], pmask)
        if qa != q:
            _read_outputs(acc2, outputs[qa], pmask)
        if qb != qa:
            _read_outputs(acc3, outputs[qb], pmask)
        if qc != qb:
            _read_outputs(acc4, outputs[qc], pmask)
