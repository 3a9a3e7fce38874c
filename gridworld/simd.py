"""The predictor's step on a group of lanes in explicit 16-float vectors.

A lane (one agent of one run) keeps its predictor's hidden units as one row of 16 float32
(units beyond H_p stay 0), and the input sums come from a table with one such row per input
pattern. One step of :data:`GROUP` lanes is written here in LLVM's vector instructions, as a
numba intrinsic, because numba's loops do not vectorise across a lane's units (LLVM unrolls the
loop over the units first). A group of 16 lanes:

1. per lane, the input sums (one row load) plus the self-loops times the last state, then the
   rational tanh of :func:`gridworld.kernels.tanh_fast`, operation for operation, so the states
   are the same to the bit as computed one unit at a time;
2. the 16 lanes' states transposed (16 rows of units into 16 vectors of lanes, four rounds of
   shuffles), then each sensor's output sum on all 16 lanes at once: unit j's vector times the
   weight ``weights[j, k]`` (unit j to sensor k), fused multiply-adds in two partial sums (even
   and odd units: half the chain of dependent operations). That estimate lies within
   ``margin[k]`` (:data:`gridworld.predictor.OUTPUT_MARGIN` times the output's absolute weights)
   of the code's sum, so its sign is the code's where it is farther from zero than that (a NaN
   estimate counts as near, and the code's rule decides it);
3. the prediction bits: sensor k is 1 where its estimate is 0 or more, only the sensors in
   ``keep``, over the fixed ones in ``first``.

The lanes whose estimate lay within a margin come back as set bits of the result (bit l: lane
a + l); :mod:`gridworld.predictor` then computes their sums the code's way. What each step costs,
and the layouts tried, are in docs/gridworld.md ("Speed, and agreement with the authors' code").

Without numba, :func:`step_lanes` and :func:`read_lanes` are plain Python of the same meaning
(their estimate is the code's sum itself).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from gridworld.kernels import TANH_FAST_CONSTANTS, tanh_fast
from minimize_surprise.jit import JIT

__all__ = ["GROUP", "UNITS", "read_lanes", "row_add", "step_lanes"]

#: Floats in a lane's row: hidden units (and sensors) a vector holds.
UNITS = 16
#: Lanes one call steps; the predictor's lanes are padded to a multiple of it.
GROUP = 16
#: States whose tanh is written out step by step together, so that their chains interleave (the
#: sizes tried: docs/gridworld.md).
WAVE = 4
#: Hidden units the output sums take, and sensors they predict: the most any predictor has (the
#: full network pair of the 14-sensor model has 14 of each); a row's units 14 and 15 stay 0.
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
        for k in range(TERMS):
            z = np.float32(0.0)
            for j in range(TERMS):
                z = np.float32(z + hidden[a + lane, j] * weights[j, k])
            bits |= (1 << k) if z >= 0.0 else 0
            if not abs(z) > margin[k]:
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


def _row_add_py(out: np.ndarray, dst: int, src: int, terms: np.ndarray, i: int) -> None:
    out[dst] = out[src] + terms[i]


def _intrinsics() -> tuple[Any, Any, Any]:
    # The intrinsics, built only where numba is (its import is deferred like the kernels').
    from llvmlite import ir  # type: ignore[import-untyped]
    from numba import types
    from numba.core import cgutils
    from numba.extending import intrinsic

    f32 = ir.FloatType()
    i32 = ir.IntType(32)
    i64 = ir.IntType(64)
    vec = ir.VectorType(f32, UNITS)
    ivec = ir.VectorType(i32, UNITS)

    def splat(value: Any) -> Any:
        return ir.Constant(vec, [ir.Constant(f32, float(np.float32(value)))] * UNITS)

    def tanh(b: Any, xs: list[Any]) -> list[Any]:
        # kernels.tanh_fast on vectors of 16 floats: the same operations in the same order, none
        # fused; written step by step across the vectors, so that their chains interleave
        clamp, numerator, denominator = TANH_FAST_CONSTANTS
        high, low = splat(clamp), splat(-clamp)
        xs = [b.select(b.fcmp_ordered(">", x, high), high, x) for x in xs]
        xs = [b.select(b.fcmp_ordered("<", x, low), low, x) for x in xs]
        x2s = [b.fmul(x, x) for x in xs]
        ps = [b.fadd(b.fmul(x2, splat(numerator[0])), splat(numerator[1])) for x2 in x2s]
        qs = [b.fadd(b.fmul(x2, splat(denominator[0])), splat(denominator[1])) for x2 in x2s]
        for c in numerator[2:]:
            ps = [b.fadd(b.fmul(x2, p), splat(c)) for x2, p in zip(x2s, ps, strict=True)]
        for c in denominator[2:]:
            qs = [b.fadd(b.fmul(x2, q), splat(c)) for x2, q in zip(x2s, qs, strict=True)]
        ps = [b.fmul(x, p) for x, p in zip(xs, ps, strict=True)]
        return [b.fdiv(p, q) for p, q in zip(ps, qs, strict=True)]

    def row(context: Any, b: Any, array_type: Any, array: Any, index: Any) -> Any:
        # a pointer to the 16 floats of row `index` of a (rows, 16) C-contiguous array
        data = context.make_array(array_type)(context, b, array).data
        return b.bitcast(b.gep(data, [b.mul(index, ir.Constant(i64, UNITS))]), vec.as_pointer())

    def transpose(b: Any, rows: list[Any]) -> list[Any]:
        # 16 rows of 16 into 16 columns: four rounds, each swapping one bit of the row index
        # with the same bit of the column index (two-source shuffles, one instruction each)
        for m in range(4):
            bit = 1 << m
            lo_mask = [j if j & bit == 0 else UNITS + (j ^ bit) for j in range(UNITS)]
            hi_mask = [j | bit if j & bit == 0 else UNITS + j for j in range(UNITS)]
            swapped = list(rows)
            for lo in range(UNITS):
                if lo & bit == 0:
                    pair = rows[lo], rows[lo | bit]
                    swapped[lo] = b.shuffle_vector(*pair, ir.Constant(ivec, lo_mask))
                    swapped[lo | bit] = b.shuffle_vector(*pair, ir.Constant(ivec, hi_mask))
            rows = swapped
        return rows

    def outputs(context: Any, b: Any, states: list[Any], at: Any, sig: Any, args: Any) -> Any:
        # steps 2 and 3 for the group's states; args end in weights, margin, pmask, keep, first
        wt, mt, pt = sig.args[-5:-2]
        weights, margin, pmask, keep, first = args[-5:]
        units = transpose(b, states)  # units[j][lane]: unit j's state on each lane
        wdata = context.make_array(wt)(context, b, weights).data
        mdata = context.make_array(mt)(context, b, margin).data
        pdata = context.make_array(pt)(context, b, pmask).data
        fma = cgutils.get_or_insert_function(
            b.module, ir.FunctionType(vec, [vec, vec, vec]), "llvm.fmuladd.v16f32"
        )
        fabs = cgutils.get_or_insert_function(
            b.module, ir.FunctionType(vec, [vec]), "llvm.fabs.v16f32"
        )

        def broadcast(data: Any, index: int) -> Any:
            value = b.load(b.gep(data, [ir.Constant(i64, index)]))
            return b.shuffle_vector(
                b.insert_element(ir.Constant(vec, None), value, ir.Constant(i32, 0)),
                ir.Constant(vec, None),
                ir.Constant(ivec, [0] * UNITS),
            )

        zero = splat(0.0)
        nobit = ir.Constant(ivec, [0] * UNITS)
        bits = b.shuffle_vector(
            b.insert_element(ir.Constant(ivec, None), first, ir.Constant(i32, 0)),
            ir.Constant(ivec, None),
            ir.Constant(ivec, [0] * UNITS),
        )
        near: Any = None
        for k in range(TERMS):  # sensor k's sum on every lane
            # two partial sums (even and odd units): the chains of dependent operations halve
            part = [b.fmul(units[j], broadcast(wdata, j * UNITS + k)) for j in (0, 1)]
            for j in range(2, TERMS):
                part[j % 2] = b.call(fma, [units[j], broadcast(wdata, j * UNITS + k), part[j % 2]])
            o = b.fadd(part[0], part[1])
            yes = ir.Constant(ivec, [1 << k] * UNITS)
            bits = b.or_(bits, b.select(b.fcmp_ordered(">=", o, zero), yes, nobit))
            close = b.fcmp_unordered("<=", b.call(fabs, [o]), broadcast(mdata, k))
            near = close if near is None else b.or_(near, close)
        keep_all = b.shuffle_vector(
            b.insert_element(ir.Constant(ivec, None), b.or_(keep, first), ir.Constant(i32, 0)),
            ir.Constant(ivec, None),
            ir.Constant(ivec, [0] * UNITS),
        )
        target = b.bitcast(b.gep(pdata, [at]), ivec.as_pointer())
        b.store(b.and_(bits, keep_all), target, align=4)
        return b.zext(b.bitcast(near, ir.IntType(UNITS)), i64)

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
            states = [h for w in range(0, GROUP, WAVE) for h in tanh(b, pre[w : w + WAVE])]
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

    @intrinsic
    def row_add(typingctx: Any, out: Any, dst: Any, src: Any, terms: Any, i: Any) -> Any:
        if not arrays_ok((out, types.float32), (terms, types.float32)):
            return None
        sig = types.none(out, types.int64, types.int64, terms, types.int64)

        def codegen(context: Any, b: Any, sig: Any, args: Any) -> Any:
            out_t, _, _, terms_t, _ = sig.args
            total = b.fadd(
                b.load(row(context, b, out_t, args[0], args[2]), align=4),
                b.load(row(context, b, terms_t, args[3], args[4]), align=4),
            )
            b.store(total, row(context, b, out_t, args[0], args[1]), align=4)
            return context.get_dummy_value()

        return sig, codegen

    return step_lanes, read_lanes, row_add


#: ``step_lanes(table, pkey, hidden, a, self_loop, weights, margin, pmask, keep, first)``:
#: lanes a .. a + GROUP - 1 one step on (module docstring): their states in ``hidden`` ((lanes,
#: 16) float32) from inputs ``pkey`` (int32) and ``table`` ((patterns, 16)), their predictions
#: into ``pmask``; returns the lanes (bit l: lane a + l) with a sum too near zero to read.
step_lanes: Callable[..., int]
#: ``read_lanes(hidden, a, weights, margin, pmask, keep, first)``: steps 2 and 3 alone, for
#: states already computed (the code's exact tanh).
read_lanes: Callable[..., int]
#: ``row_add(out, dst, src, terms, i)``: row ``dst`` of ``out`` becomes row ``src`` plus row ``i``
#: of ``terms`` (both (rows, 16) float32), as one vector addition.
row_add: Callable[..., None]
if JIT:
    step_lanes, read_lanes, row_add = _intrinsics()
else:
    step_lanes, read_lanes, row_add = _step_lanes_py, _outputs_py, _row_add_py
