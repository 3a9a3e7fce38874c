"""The grid world's compiled pieces: the torus's tables, the networks' arithmetic, the noise.

:mod:`gridworld.runs` runs whole generations with them. The named structures here
(:class:`Torus`, :class:`WorldTables`, :class:`Noise`) are what the kernels take. Both networks
take their hidden units' input sums from a per-genome table of the sums over all inputs for every
pattern of their bits (:func:`prefix_sums`; the predictor's by pattern,
:func:`gridworld.predictor.input_sums`): the authors' float32 operations, so their sums bit for
bit, at a fraction of the work. The actor's decision (:func:`actor_decision`) is computed with a
fast tanh and again with the code's tanh only when an output lies too near zero for the fast one
to decide its sign; :func:`actor_decisions` computes it for every input at once. The predictor's
hidden units use :func:`tanh_fast` (a rational approximation good to float32 rounding) unless
``exact`` asks for the code's exp-based tanh.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from minimize_surprise.gridnet import c_activation, c_negative
from minimize_surprise.jit import kernel
from minimize_surprise.rng import mix32

__all__ = [
    "TANH_FAST_CONSTANTS",
    "Noise",
    "Torus",
    "WorldTables",
    "actor_decision",
    "actor_decisions",
    "build_torus",
    "noise_bits",
    "prefix_sums",
    "tanh_fast",
    "world_tables",
]


# The kernels' arguments as named structures (numba takes named tuples whole). A kernel reads
# their fields into locals once, at its top: a field read inside a hot loop costs a reference
# count update each time.


class WorldTables(NamedTuple):
    """The torus's lookup tables, the same for every genome and run (:func:`world_tables`)."""

    front_of: np.ndarray
    sense: np.ndarray
    row_of: np.ndarray
    col_of: np.ndarray
    row_bits: np.ndarray
    col_bits: np.ndarray


class Torus(NamedTuple):
    """The world every run of a batch lives in: ``nb`` (cells, 4, R) the cell each sensor of an
    agent reads per cell and heading; ``window`` the sensor model as bit windows
    (:func:`gridworld.world.window_table`; empty: read cell by cell); ``width``; ``tables``."""

    nb: np.ndarray
    window: np.ndarray
    width: int
    tables: WorldTables


class Noise(NamedTuple):
    """Sensor noise: a reading flips when its 32 random bits (drawn from ``key``) fall below
    ``threshold`` (0: no noise)."""

    threshold: int
    key: int


# float32 constants keep the rational tanh in single precision (twice the lanes per vector)
_CLAMP = np.float32(7.90531110763549805)
_A13 = np.float32(-2.76076847742355e-16)
_A11 = np.float32(2.00018790482477e-13)
_A9 = np.float32(-8.60467152213735e-11)
_A7 = np.float32(5.12229709037114e-08)
_A5 = np.float32(1.48572235717979e-05)
_A3 = np.float32(6.37261928875436e-04)
_A1 = np.float32(4.89352455891786e-03)
_B6 = np.float32(1.19825839466702e-06)
_B4 = np.float32(1.18534705686654e-04)
_B2 = np.float32(2.26843463243900e-03)
_B0 = np.float32(4.89352518554385e-03)

#: :func:`tanh_fast`'s constants for code that writes it out (:mod:`gridworld.simd`): the clamp,
#: the numerator's coefficients from the highest power down, the denominator's.
TANH_FAST_CONSTANTS = (_CLAMP, (_A13, _A11, _A9, _A7, _A5, _A3, _A1), (_B6, _B4, _B2, _B0))


@kernel
def tanh_fast(x: np.float32) -> np.float32:
    """tanh of a float32 by a rational approximation (absolute error below 3e-7; its divisor is
    never 0, and without branches or division checks the loops that call it vectorise)."""
    x = _CLAMP if x > _CLAMP else x
    x = -_CLAMP if x < -_CLAMP else x
    x2 = x * x
    p = x2 * _A13 + _A11
    p = x2 * p + _A9
    p = x2 * p + _A7
    p = x2 * p + _A5
    p = x2 * p + _A3
    p = x2 * p + _A1
    p = x * p
    q = x2 * _B6 + _B4
    q = x2 * q + _B2
    q = x2 * q + _B0
    return p / q


@kernel
def prefix_sums(u: np.ndarray, w: np.ndarray, g: int, bits: int, out: np.ndarray) -> None:
    """Input-layer sums of genome ``g`` over its first ``bits`` inputs for every pattern of their
    bits: ``out[j, k]`` = u[g, bit_0(k), 0] * w[g, j, 0] + u[g, bit_1(k), 1] * w[g, j, 1] + ...
    for hidden unit j, in float32 and in input order as the code adds them (``u``: (G, 2, I)
    input units, ``w``: (G, H, I) weights, ``out``: (H, 2^bits)).

    A sum over all inputs is then the table's entry for the low bits continued by the remaining
    inputs in order: the same float32 operations as summing from zero, so the same result. The
    table is built one input at a time, each level from the one before (2^(bits+1) additions
    per unit).
    """
    for j in range(w.shape[1]):
        row = out[j]
        row[0] = 0.0
        for i in range(bits):
            half = 1 << i
            t0 = u[g, 0, i] * w[g, j, i]
            t1 = u[g, 1, i] * w[g, j, i]
            for k in range(half):
                row[k + half] = row[k] + t1
                row[k] = row[k] + t0


#: An approximate actor output farther from zero than this share of its weights' absolute sum
#: has the exact output's sign: tanh_fast is within 3e-7 of tanh, the code's tanh within float32
#: rounding of it, and float32 sums of at most 8 products add rounding of the same order.
SIGN_MARGIN = np.float32(3e-6)


@kernel
def actor_decision(
    a_u: np.ndarray,
    a_hidden: np.ndarray,
    a_out: np.ndarray,
    g: int,
    key: int,
    inputs: int,
    prefix: np.ndarray,
    bits: int,
    scratch: np.ndarray,
) -> int:
    """Genome ``g``'s decision for the input bits in ``key`` (bit i = input i) by the code's
    arithmetic: a0 + 2 * (1 if it turns left). ``prefix`` is :func:`prefix_sums` of the actor
    over its first ``bits`` inputs; ``scratch`` holds at least H_a float32 values.

    Every hidden unit's sum runs over the inputs in order, in float32, as in the code. The
    outputs are first computed with :func:`tanh_fast`; only an output within ``SIGN_MARGIN``
    of zero is computed again with the code's tanh, so the decision is always the code's.
    """
    ha = a_hidden.shape[1]
    low = key & ((1 << bits) - 1)
    for j in range(ha):
        scratch[j] = prefix[j, low]
    for i in range(bits, inputs):
        u = a_u[g, (key >> i) & 1, i]
        for j in range(ha):
            scratch[j] += u * a_hidden[g, j, i]
    z0 = np.float32(0.0)
    z1 = np.float32(0.0)
    m0 = np.float32(0.0)
    m1 = np.float32(0.0)
    for j in range(ha):
        h = tanh_fast(scratch[j])
        z0 += h * a_out[g, 0, j]
        z1 += h * a_out[g, 1, j]
        m0 += abs(a_out[g, 0, j])
        m1 += abs(a_out[g, 1, j])
    if abs(z0) <= SIGN_MARGIN * m0 + 1e-9 or abs(z1) <= SIGN_MARGIN * m1 + 1e-9:
        z0 = np.float32(0.0)
        z1 = np.float32(0.0)
        for j in range(ha):
            h = c_activation(scratch[j])
            z0 += h * a_out[g, 0, j]
            z1 += h * a_out[g, 1, j]
    a0 = 0 if c_negative(z0) else 1
    left = 1 if c_negative(z1) else 0
    return a0 + 2 * left


@kernel
def actor_decisions(
    a_u: np.ndarray,
    a_hidden: np.ndarray,
    a_out: np.ndarray,
    g: int,
    sums: np.ndarray,
    z: np.ndarray,
    memo: np.ndarray,
) -> None:
    """Genome ``g``'s decision (as :func:`actor_decision` returns it) for every pattern of its
    input bits into ``memo`` ((2^I,) int8), computed for all patterns at once: a loop over the
    patterns per hidden unit, which vectorises (``sums``: (H_a, 2^I) and ``z``: (2, 2^I)
    float32, room).

    The same arithmetic as :func:`actor_decision` pattern by pattern: the input sums over all
    inputs (:func:`prefix_sums`, the same additions as its table continued input by input), the
    outputs' sums with :func:`tanh_fast` in unit order, and a pattern with an output within its
    margin of zero handed to :func:`actor_decision` itself; so every decision is its decision.
    """
    inputs, ha = a_u.shape[2], a_hidden.shape[1]
    patterns = 1 << inputs
    prefix_sums(a_u, a_hidden, g, inputs, sums)
    z0, z1 = z[0], z[1]
    for k in range(patterns):
        z0[k] = 0.0
        z1[k] = 0.0
    m0 = np.float32(0.0)
    m1 = np.float32(0.0)
    for j in range(ha):
        row = sums[j]
        w0, w1 = a_out[g, 0, j], a_out[g, 1, j]
        m0 += abs(w0)
        m1 += abs(w1)
        for k in range(patterns):
            h = tanh_fast(row[k])
            z0[k] += h * w0
            z1[k] += h * w1
    near0 = SIGN_MARGIN * m0 + 1e-9
    near1 = SIGN_MARGIN * m1 + 1e-9
    scratch = np.empty(ha, dtype=np.float32)
    for k in range(patterns):
        if abs(z0[k]) <= near0 or abs(z1[k]) <= near1:
            memo[k] = actor_decision(a_u, a_hidden, a_out, g, k, inputs, sums, inputs, scratch)
        else:
            # a0 is 0 only for a negative sum (a NaN reads as not negative, as in c_negative)
            memo[k] = (0 if z0[k] < 0.0 else 1) + (2 if z1[k] < 0.0 else 0)


@kernel
def noise_bits(key: int, counter: int) -> int:
    # 32 random bits for one sensor reading, a pure function of the key and the reading's index.
    low = mix32(counter & 0xFFFFFFFF)
    high = mix32((counter >> 32) + 0x9E3779B9)
    return mix32(key ^ low ^ (high * 0x85EBCA6B))


@kernel(inline=True)
def _pack(first: int, second: int, third: int, shift: int) -> np.uint64:
    # three line numbers and a shift in 16 bits each (one load instead of four)
    return np.uint64(first | (second << 16) | (third << 32) | (shift << 48))


@kernel
def world_tables(nb: np.ndarray, width: int, bits_ok: bool) -> WorldTables:
    """The torus's lookup tables, the same for every genome and run (:class:`WorldTables`).

    ``front_of[4 c + d]`` is the cell in front of cell c facing d. A run's occupancy is kept as
    bit lines: the rows (by y) then the columns (by x), each doubled (bits 0..W-1 repeated above)
    so a window of 5 that wraps around is one shift. Per cell c and heading parity p,
    ``sense[2 c + p]`` holds in 16 bits each the three lines an agent there reads (bits 0, 16,
    32) and the shift that brings its window to bits 0..4 (bit 48); per cell, ``row_of`` and
    ``col_of`` name its row and column and ``row_bits``/``col_bits`` the bits it sets in them (0
    unless ``bits_ok``: sides of at most 32, so the doubled lines fit 64 bits).
    """
    cells = nb.shape[0]
    height = cells // width
    sense = np.empty(cells * 2, dtype=np.uint64)
    row_of = np.empty(cells, dtype=np.uint32)
    col_of = np.empty(cells, dtype=np.uint32)
    row_bits = np.zeros(cells, dtype=np.uint64)
    col_bits = np.zeros(cells, dtype=np.uint64)
    one = np.uint64(1)
    front_of = np.empty(cells * 4, dtype=np.uint32)
    for c in range(cells):
        x, y = c % width, c // width
        ym, yp = (y + height - 1) % height, (y + 1) % height
        xm, xp = (x + width - 1) % width, (x + 1) % width
        sense[2 * c] = _pack(ym, y, yp, (x + width - 2) % width)
        sense[2 * c + 1] = _pack(height + xm, height + x, height + xp, (y + height - 2) % height)
        row_of[c], col_of[c] = y, height + x
        if bits_ok:
            row_bits[c] = (one << np.uint64(x)) | (one << np.uint64(x + width))
            col_bits[c] = (one << np.uint64(y)) | (one << np.uint64(y + height))
        for d in range(4):
            front_of[c * 4 + d] = nb[c, d, 0]
    return WorldTables(front_of, sense, row_of, col_of, row_bits, col_bits)


def build_torus(nb: np.ndarray, window: np.ndarray, width: int) -> Torus:
    """The :class:`Torus` of neighbour table ``nb``, sensor ``window`` table (empty: read cell by
    cell) and ``width``, its :func:`world_tables` built (the bit lines need a ``window``)."""
    return Torus(nb, window, width, world_tables(nb, width, window.shape[0] > 0))
