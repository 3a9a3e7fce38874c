"""gridworld.simd's intrinsics, each compiled and run on a small input against numpy.

They write LLVM IR through numba's internals (``numba.extending.intrinsic``, the array models'
``make_array``, ``cgutils``) and llvmlite's IR builder, which a numba release may change: this
is the test to run first after a numba or llvmlite update (docs/gridworld.md, "When numba
changes"). Every intrinsic the module defines is found by its type, so a new one fails here until
it has a reference below. The grid world's own tests cover them too, through whole runs; these
say which one broke and how.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from gridworld import simd
from gridworld.kernels import TANH_FAST_CONSTANTS
from gridworld.predictor import OUTPUT_MARGIN
from minimize_surprise.jit import JIT

pytestmark = pytest.mark.skipif(not JIT, reason="the intrinsics exist only where numba is")

F32 = np.float32
UNITS, GROUP, TERMS = simd.UNITS, simd.GROUP, simd.TERMS


def _intrinsics() -> list[str]:
    from numba.core.extending import _Intrinsic

    return sorted(name for name, value in vars(simd).items() if isinstance(value, _Intrinsic))


@functools.cache
def _compiled(name: str) -> Callable[..., Any]:
    # An intrinsic runs only inside a kernel: one that passes its arguments through.
    import numba

    intrinsic = getattr(simd, name)

    @numba.njit
    def call(*args: Any) -> Any:
        return intrinsic(*args)

    return call


# --------------------------------------------------------------------------- numpy's side


def _tanh(x: np.ndarray) -> np.ndarray:
    # gridworld.kernels.tanh_fast on float32 arrays: the same operations in the same order
    clamp, numerator, denominator = TANH_FAST_CONSTANTS
    x = np.minimum(np.maximum(x, F32(-clamp)), F32(clamp))
    x2 = x * x
    p = x2 * F32(numerator[0]) + F32(numerator[1])
    for c in numerator[2:]:
        p = x2 * p + F32(c)
    q = x2 * F32(denominator[0]) + F32(denominator[1])
    for c in denominator[2:]:
        q = x2 * q + F32(c)
    return (x * p) / q


class _Outputs:
    """A predictor's output layer as gridworld.predictor builds it: sensors ``keep`` predicted
    from weights ``weights[j, k]`` (unit j to sensor k) with margins, the ``first`` bits fixed."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.keep, self.first = np.uint32(0b01_1011_0110_1011), np.uint32(0b10_0000_0001_0000)
        kept = [k for k in range(UNITS) if self.keep >> k & 1]
        self.weights = np.zeros((UNITS, UNITS), dtype=F32)
        self.weights[:TERMS, kept] = rng.normal(size=(TERMS, len(kept)))
        self.margin = np.full(UNITS, -1.0, dtype=F32)
        self.margin[kept] = OUTPUT_MARGIN * np.abs(self.weights[:, kept]).sum(axis=0) + F32(1e-9)
        self.kept = np.array(kept)

    def check(self, hidden: np.ndarray, a: int, pmask: np.ndarray, before: np.ndarray, unsure: int):
        """What read_lanes and step_lanes return and write for lanes a .. a + GROUP - 1 of
        ``hidden`` (their states), against the exact sums (float64)."""
        exact = hidden[a : a + GROUP, :TERMS].astype(np.float64) @ self.weights[:TERMS]
        bits = (exact >= 0.0) @ (1 << np.arange(UNITS))
        expected = (bits.astype(np.uint32) & self.keep) | self.first
        near = np.abs(exact[:, self.kept])
        margin = self.margin[self.kept].astype(np.float64)
        flagged = np.array([unsure >> lane & 1 for lane in range(GROUP)], dtype=bool)
        nan = np.isnan(exact[:, self.kept]).any(axis=1)
        # Where every sum is clear of its margin, the lane's estimate signs are the sums' own;
        # a sum near zero (or NaN) is flagged for the exact sums to decide.
        assert not flagged[((near > 2 * margin).all(axis=1)) & ~nan].any(), (unsure, exact)
        assert flagged[((near <= margin / 2).any(axis=1)) | nan].all(), (unsure, exact)
        written = pmask[a : a + GROUP]
        assert np.array_equal(written[~flagged], expected[~flagged]), (written, expected)
        assert np.array_equal(written & ~self.keep, np.full(GROUP, self.first & ~self.keep))
        outside = np.ones(pmask.shape[0], dtype=bool)
        outside[a : a + GROUP] = False
        assert np.array_equal(pmask[outside], before[outside])  # other lanes untouched


def _states(rng: np.random.Generator, lanes: int) -> np.ndarray:
    hidden = np.zeros((lanes, UNITS), dtype=F32)
    hidden[:, :TERMS] = rng.uniform(-1.0, 1.0, size=(lanes, TERMS))
    return hidden


# --------------------------------------------------------------------------- each intrinsic


def _check_read_lanes(rng: np.random.Generator) -> None:
    out = _Outputs(rng)
    hidden = _states(rng, 3 * GROUP)
    a = GROUP
    hidden[a + 3] = 0.0  # every sum exactly 0: flagged
    hidden[a + 5, 2] = np.nan  # NaN sums: flagged
    hidden[a + 7, :] *= F32(1e-9)  # sums far inside their margins: flagged
    pmask = rng.integers(0, 2**32, size=3 * GROUP, dtype=np.uint32)
    before = pmask.copy()
    unsure = _compiled("read_lanes")(hidden, a, out.weights, out.margin, pmask, out.keep,
                                     out.first)  # fmt: skip
    assert unsure >> 3 & 1 and unsure >> 5 & 1 and unsure >> 7 & 1
    out.check(hidden, a, pmask, before, unsure)


def _check_step_lanes(rng: np.random.Generator) -> None:
    out = _Outputs(rng)
    lanes, patterns, a = 3 * GROUP, 5, 2 * GROUP
    table = np.zeros((patterns, UNITS), dtype=F32)
    table[1:, :TERMS] = rng.normal(size=(patterns - 1, TERMS))
    self_loop = np.zeros(UNITS, dtype=F32)
    self_loop[:TERMS] = rng.normal(size=TERMS)
    pkey = rng.integers(1, patterns, size=lanes, dtype=np.int32)
    hidden = _states(rng, lanes)
    pkey[a + 4], hidden[a + 4] = 0, 0.0  # a zero row of sums on a zero state: every sum 0
    hidden[a + 9, 1] = np.nan
    start = hidden.copy()
    pmask = np.zeros(lanes, dtype=np.uint32)
    before = pmask.copy()
    unsure = _compiled("step_lanes")(table, pkey, hidden, a, self_loop, out.weights, out.margin,
                                     pmask, out.keep, out.first)  # fmt: skip
    # The states: tanh_fast of the row of sums plus the self-loops times the last state, to
    # the bit (NaN where the last state was).
    lane = slice(a, a + GROUP)
    expected = _tanh(table[pkey[lane]] + start[lane] * self_loop)
    assert np.array_equal(hidden[lane], expected, equal_nan=True)
    assert np.array_equal(hidden[:a], start[:a])  # other lanes untouched
    assert np.array_equal(hidden[a + GROUP :], start[a + GROUP :])
    assert not hidden[lane, TERMS:].any()  # units beyond the sums stay 0
    assert unsure >> 4 & 1 and unsure >> 9 & 1
    out.check(hidden, a, pmask, before, unsure)


def _check_row_add(rng: np.random.Generator) -> None:
    out = rng.normal(size=(6, UNITS)).astype(F32)
    terms = rng.normal(size=(4, UNITS)).astype(F32)
    expected = out.copy()
    expected[4] = out[1] + terms[2]
    assert _compiled("row_add")(out, 4, 1, terms, 2) is None
    assert np.array_equal(out, expected)
    expected[1] = expected[1] + terms[3]  # in place: dst == src
    _compiled("row_add")(out, 1, 1, terms, 3)
    assert np.array_equal(out, expected)


#: Each intrinsic's check against numpy; a new intrinsic needs one here.
CHECKS: dict[str, Callable[[np.random.Generator], None]] = {
    "read_lanes": _check_read_lanes,
    "row_add": _check_row_add,
    "step_lanes": _check_step_lanes,
}


def test_every_intrinsic_has_a_check() -> None:
    found = _intrinsics()
    assert found, "no intrinsic found in gridworld.simd: has numba's _Intrinsic moved?"
    assert found == sorted(CHECKS), f"gridworld.simd's intrinsics {found}, checked {sorted(CHECKS)}"


@pytest.mark.parametrize("name", sorted(CHECKS))
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_each_intrinsic_compiles_and_gives_numpys_numbers(name: str, seed: int) -> None:
    CHECKS[name](np.random.default_rng(seed))
