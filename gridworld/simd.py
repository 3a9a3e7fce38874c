"""The predictor's step on a group of lanes in explicit 16-float vectors.

A lane (one agent of one run) keeps its predictor's hidden units as one row of 16 float32
(units beyond H_p stay 0), and the input sums come from a table with one such row per input
pattern. One step of :data:`GROUP` lanes is written here in LLVM's vector instructions, as a
numba intrinsic, because numba's loops do not vectorise across a lane's units (LLVM unrolls the
loop over the units first). For each lane of the group:

1. the input sums (one row load) plus the self-loops times the last state, then the rational tanh
   of :func:`gridworld.kernels.tanh_fast`, operation for operation, so the states are the same to
   the bit as computed one unit at a time;
2. every output's sum at once: for each unit j, its state broadcast times the j-th row of the
   output weights (``weights[j, k]``: unit j to sensor k), in fused multiply-adds over two
   accumulators; that estimate lies within :data:`gridworld.predictor.OUTPUT_MARGIN` of the
   code's sum, so its sign is the code's where it is farther from zero than ``margin[k]``;
3. the prediction bits: sensor k is 1 where its estimate is 0 or more, only the sensors in
   ``keep``, over the fixed ones in ``first``.

The lanes whose estimate lay within a margin come back as set bits of the result (bit l: lane
a + l); :mod:`gridworld.predictor` then computes their sums the code's way. The lanes of a group
are written one after the other in the instruction stream so that the processor overlaps their
long chains (the tanh, the sums): one lane at a time ran 1.8 times slower.

Without numba, :func:`step_lanes` and :func:`read_lanes` are plain Python of the same meaning
(their estimate is the code's sum itself).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from gridworld.kernels import TANH_FAST_CONSTANTS, tanh_fast
from minimize_surprise.jit import JIT

__all__ = ["GROUP", "UNITS", "read_lanes", "step_lanes"]

#: Floats in a lane's row: hidden units (and sensors) a vector holds.
UNITS = 16
#: Lanes one call steps; the predictor's lanes are padded to a multiple of it.
GROUP = 8
#: Hidden units the output sums take: the most any predictor has (14 sensors' full pair);
#: the rows' units 14 and 15 are always 0.
TERMS = 14


def _tanh_py(x: np.float32) -> np.float32:
    return np.float32(tanh_fast(np.float32(x)))


def _outputs_py(
    hidden: np.ndarray,
    a: int,
    weights: np.ndarray,
    margin: np.ndarray,
    pmask: np.ndarray,
    keep: int,
    first: int,
) -> int:
    unsure = 0
    for lane in range(GROUP):
        bits = 0
        for k in range(UNITS):
            z = np.float32(0.0)
            for j in range(TERMS):
                z = np.float32(z + hidden[a + lane, j] * weights[j, k])
            bits |= (1 << k) if z >= 0.0 else 0
            if abs(z) <= margin[k]:
                unsure |= 1 << lane
        pmask[a + lane] = np.uint32((bits & keep) | first)
    return unsure


def _step_lanes_py(
    table: np.ndarray,
    pkey: np.ndarray,
    hidden: np.ndarray,
    a: int,
    self_loop: np.ndarray,
    weights: np.ndarray,
    margin: np.ndarray,
    pmask: np.ndarray,
    keep: int,
    first: int,
) -> int:
    for lane in range(GROUP):
        row = table[int(pkey[a + lane])]
        for j in range(UNITS):
            pre = np.float32(row[j] + np.float32(hidden[a + lane, j] * self_loop[j]))
            hidden[a + lane, j] = _tanh_py(pre)
    return _outputs_py(hidden, a, weights, margin, pmask, keep, first)


def _intrinsics() -> tuple[Any, Any]:
    # The two intrinsics, built only where numba is (its import is deferred like the kernels').
    from llvmlite import ir  # type: ignore[import-untyped]
    from numba import types
    from numba.core import cgutils
    from numba.extending import intrinsic

    f32 = ir.FloatType()
    i32 = ir.IntType(32)
    i64 = ir.IntType(64)
    vec = ir.VectorType(f32, UNITS)

    def splat(value: Any) -> Any:
        return ir.Constant(vec, [ir.Constant(f32, float(np.float32(value)))] * UNITS)

    def tanh(b: Any, x: Any) -> Any:
        # kernels.tanh_fast on 16 floats: the same operations in the same order, none fused
        clamp, numerator, denominator = TANH_FAST_CONSTANTS
        high, low = splat(clamp), splat(-clamp)
        x = b.select(b.fcmp_ordered(">", x, high), high, x)
        x = b.select(b.fcmp_ordered("<", x, low), low, x)
        x2 = b.fmul(x, x)
        p = b.fadd(b.fmul(x2, splat(numerator[0])), splat(numerator[1]))
        for c in numerator[2:]:
            p = b.fadd(b.fmul(x2, p), splat(c))
        p = b.fmul(x, p)
        q = b.fadd(b.fmul(x2, splat(denominator[0])), splat(denominator[1]))
        for c in denominator[2:]:
            q = b.fadd(b.fmul(x2, q), splat(c))
        return b.fdiv(p, q)

    def row(context: Any, b: Any, array_type: Any, array: Any, index: Any) -> Any:
        # a pointer to the 16 floats of row `index` of a (rows, 16) C-contiguous array
        data = context.make_array(array_type)(context, b, array).data
        return b.bitcast(b.gep(data, [b.mul(index, ir.Constant(i64, UNITS))]), vec.as_pointer())

    def outputs(context: Any, b: Any, states: list[Any], at: Any, sig: Any, args: Any) -> Any:
        # steps 2 and 3 for the lanes' states; args end in weights, margin, pmask, keep, first
        wt, mt, pt = sig.args[-5:-2]
        weights, margin, pmask, keep, first = args[-5:]
        w = [
            b.load(row(context, b, wt, weights, ir.Constant(i64, j)), align=4) for j in range(TERMS)
        ]
        mdata = context.make_array(mt)(context, b, margin).data
        m = b.load(b.bitcast(mdata, vec.as_pointer()), align=4)
        pdata = context.make_array(pt)(context, b, pmask).data
        fma = cgutils.get_or_insert_function(
            b.module, ir.FunctionType(vec, [vec, vec, vec]), "llvm.fmuladd.v16f32"
        )
        fabs = cgutils.get_or_insert_function(
            b.module, ir.FunctionType(vec, [vec]), "llvm.fabs.v16f32"
        )
        zero = splat(0.0)
        unsure = ir.Constant(i64, 0)
        for lane, h in enumerate(states):
            sums: list[Any] = [None, None]
            for j in range(TERMS):
                hj = b.shuffle_vector(
                    h, ir.Constant(vec, None), ir.Constant(ir.VectorType(i32, UNITS), [j] * UNITS)
                )
                s = j % 2
                sums[s] = b.fmul(hj, w[j]) if sums[s] is None else b.call(fma, [hj, w[j], sums[s]])
            o = b.fadd(sums[0], sums[1])
            near = b.fcmp_ordered("<=", b.call(fabs, [o]), m)
            bits = b.zext(b.bitcast(b.fcmp_ordered(">=", o, zero), ir.IntType(UNITS)), i32)
            bits = b.or_(b.and_(bits, keep), first)
            b.store(bits, b.gep(pdata, [b.add(at, ir.Constant(i64, lane))]))
            flag = b.icmp_unsigned(
                "!=", b.bitcast(near, ir.IntType(UNITS)), ir.Constant(ir.IntType(UNITS), 0)
            )
            unsure = b.or_(unsure, b.shl(b.zext(flag, i64), ir.Constant(i64, lane)))
        return unsure

    def arrays_ok(*arrays: Any) -> bool:
        return all(
            isinstance(t, types.Array) and t.layout == "C" and t.dtype == d for t, d in arrays
        )

    @intrinsic
    def step_lanes(
        typingctx: Any, table: Any, pkey: Any, hidden: Any, a: Any, self_loop: Any,
        weights: Any, margin: Any, pmask: Any, keep: Any, first: Any,
    ) -> Any:  # fmt: skip
        f, u = types.float32, types.uint32
        if not arrays_ok((table, f), (pkey, types.int32), (hidden, f), (self_loop, f),
                         (weights, f), (margin, f), (pmask, u)):  # fmt: skip
            return None
        sig = types.int64(table, pkey, hidden, types.int64, self_loop, weights, margin, pmask,
                          u, u)  # fmt: skip

        def codegen(context: Any, b: Any, sig: Any, args: Any) -> Any:
            table_t, pkey_t, hidden_t, _, self_t = sig.args[:5]
            at = args[3]
            keys = context.make_array(pkey_t)(context, b, args[1]).data
            sdata = context.make_array(self_t)(context, b, args[4]).data
            s = b.load(b.bitcast(sdata, vec.as_pointer()), align=4)
            pre, rows = [], []
            for lane in range(GROUP):
                la = b.add(at, ir.Constant(i64, lane))
                key = b.zext(b.load(b.gep(keys, [la])), i64)
                sums = b.load(row(context, b, table_t, args[0], key), align=4)
                where = row(context, b, hidden_t, args[2], la)
                pre.append(b.fadd(sums, b.fmul(b.load(where, align=4), s)))
                rows.append(where)
            states = [tanh(b, x) for x in pre]
            for h, where in zip(states, rows, strict=True):
                b.store(h, where, align=4)
            return outputs(context, b, states, at, sig, args)

        return sig, codegen

    @intrinsic
    def read_lanes(
        typingctx: Any, hidden: Any, a: Any, weights: Any, margin: Any, pmask: Any, keep: Any,
        first: Any,
    ) -> Any:  # fmt: skip
        f, u = types.float32, types.uint32
        if not arrays_ok((hidden, f), (weights, f), (margin, f), (pmask, u)):
            return None
        sig = types.int64(hidden, types.int64, weights, margin, pmask, u, u)

        def codegen(context: Any, b: Any, sig: Any, args: Any) -> Any:
            at = args[1]
            states = [
                b.load(
                    row(context, b, sig.args[0], args[0], b.add(at, ir.Constant(i64, lane))),
                    align=4,
                )
                for lane in range(GROUP)
            ]
            return outputs(context, b, states, at, sig, args)

        return sig, codegen

    return step_lanes, read_lanes


#: ``step_lanes(table, pkey, hidden, a, self_loop, weights, margin, pmask, keep, first)``:
#: lanes a .. a + GROUP - 1 one step on (module docstring): their states in ``hidden`` ((lanes,
#: 16) float32) from inputs ``pkey`` (int32) and ``table`` ((patterns, 16)), their predictions
#: into ``pmask``; returns the lanes (bit l: lane a + l) with a sum too near zero to read.
step_lanes: Callable[..., int]
#: ``read_lanes(hidden, a, weights, margin, pmask, keep, first)``: steps 2 and 3 alone, for
#: states already computed (the code's exact tanh).
read_lanes: Callable[..., int]
if JIT:
    step_lanes, read_lanes = _intrinsics()
else:
    step_lanes, read_lanes = _step_lanes_py, _outputs_py
