"""Compiled simulation of the grid world: whole generations in one call.

One run of one genome from one start configuration goes as the authors' code does it. Each step
t = 0 ... T-1: (1) the occupancy of the start of the step is the snapshot every agent senses;
(2) for each agent in index order its sensors are read, last step's prediction is scored against
them, the actor decides, the predictor predicts the next reading, and its new pose is computed: a
forward move succeeds only if the front cell is empty in the snapshot and no agent of lower index
has moved into it during this step (so conflicts go to the lower index and nobody enters a cell
being vacated), a turn always succeeds; (3) all agents take their new poses.

Sensing is synchronous, so the networks of all agents of a step are computed together (the
predictor vectorised across agents); only the moves are resolved one agent after the other. Both
networks start their hidden units' input sums from a per-genome table of the sums over the first
inputs for every pattern of their bits (:func:`prefix_sums`) and continue them over the remaining
inputs in order: the code's float32 operations, so its sums bit for bit, at a quarter of the
work. The actor has no state: its decision is a function of the R + 1 input bits, computed the
first time a genome meets an input and looked up afterwards; it is computed with a fast tanh and
computed again with the code's tanh only when an output lies too near zero for the fast one to
decide its sign, so the decision is the code's. The predictor's hidden units use
:func:`tanh_fast` (a rational approximation good to float32 rounding) unless ``exact`` asks for
the code's exp-based tanh: trajectories never depend on it, only the rare prediction whose output
lies within float32 rounding of zero can.

Sensor noise flips each sensor value an agent reads with probability ``noise`` (independent per
run, step, agent and sensor; the same flips for every genome given the same ``noise_key``). The
noisy values go into both networks and the fitness; moves are blocked by true occupancy only.
"""

from __future__ import annotations

import numpy as np

from minimize_surprise.gridnet import c_activation, c_negative
from minimize_surprise.jit import kernel
from minimize_surprise.rng import mix32

__all__ = ["actor_decision", "evaluate_batch", "prefix_sums", "tanh_fast"]

#: Inputs whose input-layer sums are tabled for every pattern of their bits, per genome.
PREFIX_BITS = 11


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


@kernel(error_model="numpy")
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


@kernel(error_model="numpy")
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
def _read_outputs(
    acc: np.ndarray, sensor: int, q: int, pmask: np.ndarray, ones: np.ndarray
) -> None:
    # Output q's net inputs to prediction bits of its sensor in pmask, counted in ones[q].
    tiny = False
    for a in range(acc.shape[0]):
        bit = acc[a] >= 0.0
        pmask[a] |= np.int64(bit) << sensor
        ones[q, a] += bit
        tiny |= (acc[a] < 0.0) & (acc[a] > -1e-10)
    if tiny:  # where the code's tanh may round to 0, let it decide
        for a in range(acc.shape[0]):
            if acc[a] < 0.0 and not c_negative(acc[a]):
                pmask[a] |= np.int64(1) << sensor
                ones[q, a] += 1


@kernel
def _noise_bits(key: int, counter: int) -> int:
    # 32 random bits for one sensor reading, a pure function of the key and the reading's index.
    low = mix32(counter & 0xFFFFFFFF)
    high = mix32((counter >> 32) + 0x9E3779B9)
    return mix32(key ^ low ^ (high * 0x85EBCA6B))


@kernel
def world_tables(nb: np.ndarray, width: int, bits_ok: bool) -> tuple:
    """The torus's lookup tables, the same for every genome and run: ``(front_of, sense_line,
    sense_shift, row_of, col_of, row_bits, col_bits, popcount)``.

    ``front_of[4 c + d]`` is the cell in front of cell c facing d. A run's occupancy is kept as
    bit lines: the rows (by y) then the columns (by x), each doubled (bits 0..W-1 repeated above)
    so a window of 5 that wraps around is one shift. Per cell c and heading parity p,
    ``sense_line[2 c + p]`` names the three lines an agent there reads and ``sense_shift`` the
    shift that brings its window to bits 0..4; per cell, ``row_of``/``col_of`` name its row and
    column and ``row_bits``/``col_bits`` the bits it sets in them (0 unless ``bits_ok``: sides of
    at most 32, so the doubled lines fit 64 bits). ``popcount[v]`` counts the bits of v < 2^R.
    """
    cells, r = nb.shape[0], nb.shape[2]
    height = cells // width
    sense_line = np.empty((cells * 2, 3), dtype=np.uint32)
    sense_shift = np.empty(cells * 2, dtype=np.uint64)
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
        sense_line[2 * c, 0], sense_line[2 * c, 1], sense_line[2 * c, 2] = ym, y, yp
        sense_shift[2 * c] = (x + width - 2) % width
        sense_line[2 * c + 1, 0] = height + xm
        sense_line[2 * c + 1, 1] = height + x
        sense_line[2 * c + 1, 2] = height + xp
        sense_shift[2 * c + 1] = (y + height - 2) % height
        row_of[c], col_of[c] = y, height + x
        if bits_ok:
            row_bits[c] = (one << np.uint64(x)) | (one << np.uint64(x + width))
            col_bits[c] = (one << np.uint64(y)) | (one << np.uint64(y + height))
        for d in range(4):
            front_of[c * 4 + d] = nb[c, d, 0]
    popcount = np.zeros(1 << r, dtype=np.uint8)
    for v in range(1, 1 << r):
        popcount[v] = popcount[v >> 1] + (v & 1)
    return front_of, sense_line, sense_shift, row_of, col_of, row_bits, col_bits, popcount


@kernel(error_model="numpy")
def simulate_genome(
    nb: np.ndarray,
    window: np.ndarray,
    width: int,
    tables: tuple,
    starts: np.ndarray,
    steps: int,
    g: int,
    a_u: np.ndarray,
    a_hidden: np.ndarray,
    a_out: np.ndarray,
    p_u: np.ndarray,
    p_hidden: np.ndarray,
    p_self: np.ndarray,
    p_out: np.ndarray,
    outputs: np.ndarray,
    fixed: np.ndarray,
    memo: np.ndarray,
    noise_threshold: int,
    noise_key: int,
    exact: bool,
    correct: np.ndarray,
    predsum: np.ndarray,
    final: np.ndarray,
    trace: np.ndarray,
    trace_rep: int,
) -> None:
    """Genome ``g`` of the batch on every start configuration of ``starts`` ((reps, N, 2): cell,
    heading), the runs side by side so the networks work on reps x N agents at once.

    Per run ``rep``: ``correct[rep]`` gets the number of correct predictions, ``predsum[rep]``
    (R,) the scored predictions summed over steps and agents, ``final[rep]`` (N, 2) the poses
    after the last step. Run ``trace_rep`` (-1: none) has its poses before every step and after
    the last written to ``trace`` ((T + 1, N, 2)). ``tables`` is :func:`world_tables` of the
    torus. ``memo`` caches the actor's decisions by
    input bits (-1: not yet known). ``window`` is :func:`gridworld.world.window_table` for the
    sensor model when both sides lie in 5 ... 32: sensors are then read from bit rows and
    columns of the occupancy; with an empty ``window`` they are looked up cell by cell.
    """
    cells, r = nb.shape[0], nb.shape[2]
    reps, n = starts.shape[0], starts.shape[1]
    lanes = reps * n
    inputs = r + 1
    hp = p_hidden.shape[1]
    o = outputs.shape[0]
    cell = np.empty(lanes, dtype=np.uint32)
    head = np.empty(lanes, dtype=np.uint32)
    for rep in range(reps):
        for a in range(n):
            cell[rep * n + a] = starts[rep, a, 0]
            head[rep * n + a] = starts[rep, a, 1]
    a0 = np.zeros(lanes, dtype=np.int64)
    left = np.zeros(lanes, dtype=np.int64)
    # the last event of each cell of each run: 2 * time + 1 when an agent entered it (or stood
    # on it at the start, time 0), 2 * time when it was left, with time t + 1 for step t. A cell
    # is occupied at the start of a step if its last event is an entry, and taken or being left
    # this step if its last event is this step's: one load decides a forward move.
    event = np.zeros((reps, cells), dtype=np.int32)
    nbf = nb.ravel()
    # per agent: the sensor bits read this step with this step's a0 above them (the predictor's
    # inputs), and the bits of the prediction to be scored at the next step
    pkey = np.zeros(lanes, dtype=np.int32)
    scratch = np.zeros(a_hidden.shape[1], dtype=np.float32)
    key = np.zeros(lanes, dtype=np.int64)
    base = np.zeros(lanes, dtype=np.int64)
    flips = np.zeros(n * r, dtype=np.uint8)
    # each run's occupancy as bit lines (rows by y, then columns by x; see world_tables)
    bits_ok = window.shape[0] > 0
    lines = np.zeros((reps, cells // width + width), dtype=np.uint64)
    front_of, sense_line, sense_shift, row_of, col_of, row_bits, col_bits, popcount = tables
    five = np.uint64(31)
    first = 0
    for k in range(r):
        first |= np.int64(fixed[k]) << k
    pmask = np.full(lanes, first, dtype=np.int64)
    hidden = np.zeros((hp, lanes), dtype=np.float32)
    bits = min(PREFIX_BITS, inputs)
    low_mask = (1 << bits) - 1
    # both networks' input-layer sums over the first inputs, for every pattern of their bits
    a_prefix = np.empty((a_hidden.shape[1], 1 << bits), dtype=np.float32)
    prefix_sums(a_u, a_hidden, g, bits, a_prefix)
    p_prefix = np.empty((hp, 1 << bits), dtype=np.float32)
    prefix_sums(p_u, p_hidden, g, bits, p_prefix)
    # each agent's table column (unsigned, as every index of a per-agent loop: a signed index
    # costs a check for negative values that keeps the loop from being compiled tightly)
    low = np.zeros(lanes, dtype=np.uint32)
    acc = np.empty(lanes, dtype=np.float32)
    acc2 = np.empty(lanes, dtype=np.float32)
    acc3 = np.empty(lanes, dtype=np.float32)
    acc4 = np.empty(lanes, dtype=np.float32)
    counts = np.zeros((reps, r), dtype=np.int64)
    # per output and agent: how many of its predictions said 1
    ones = np.zeros((max(o, 1), lanes), dtype=np.int32)
    learned = np.zeros(r, dtype=np.bool_)
    for q in range(o):
        learned[outputs[q]] = True
    for rep in range(reps):
        correct[rep] = 0
        for a in range(rep * n, rep * n + n):
            c = cell[a]
            event[rep, c] = 1
            lines[rep, row_of[c]] |= row_bits[c]
            lines[rep, col_of[c]] |= col_bits[c]
    for t in range(steps):
        if trace_rep >= 0:
            for a in range(n):
                trace[t, a, 0] = cell[trace_rep * n + a]
                trace[t, a, 1] = head[trace_rep * n + a]
        # sensing on each run's snapshot (three 5-bit windows of its bit lines per agent, or
        # sensor by sensor), scoring last step's predictions
        for rep in range(reps):
            event_r = event[rep]
            lines_r = lines[rep]
            lo, hi = rep * n, rep * n + n
            if bits_ok:
                for a in range(np.uint64(lo), np.uint64(hi)):
                    d = head[a]
                    i = np.uint32(2) * cell[a] + (d & np.uint32(1))
                    s0 = sense_shift[i]
                    w0 = (lines_r[sense_line[i, 0]] >> s0) & five
                    w1 = (lines_r[sense_line[i, 1]] >> s0) & five
                    w2 = (lines_r[sense_line[i, 2]] >> s0) & five
                    key[a] = window[d, 0, w0] | window[d, 1, w1] | window[d, 2, w2]
            else:
                for a in range(lo, hi):
                    base[a] = (cell[a] * 4 + head[a]) * r
                    key[a] = 0
                for k in range(r):
                    for a in range(lo, hi):
                        key[a] |= np.int64(event_r[nbf[base[a] + k]] & 1) << k
            if noise_threshold > 0:
                # reading k of agent a has the counter origin + (a - lo) * r + k: the flips of a
                # whole run are drawn in one loop that vectorises, then set into the keys
                origin = ((rep * steps) + t) * n * r
                for m in range(n * r):
                    flips[m] = _noise_bits(noise_key, origin + m) < noise_threshold
                for a in range(lo, hi):
                    flipped = 0
                    for k in range(r):
                        flipped |= np.int64(flips[(a - lo) * r + k]) << k
                    key[a] ^= flipped
            wrong = 0
            for a in range(lo, hi):
                wrong += popcount[np.uint64(key[a] ^ pmask[a])]
            correct[rep] += n * r - wrong
        # the actor: its decision for these input bits, computed once per genome and input
        for a in range(lanes):
            full = np.uint64(key[a] | (a0[a] << r))
            m = memo[full]
            if m < 0:
                m = actor_decision(a_u, a_hidden, a_out, g, full, inputs, a_prefix, bits, scratch)
                memo[full] = m
            a0[a] = m & 1
            left[a] = m >> 1
            pkey[a] = np.int32(key[a] | ((m & 1) << r))
        # predictor on all agents of all runs: the input layer (the table's sums over the
        # first inputs, continued in order), the hidden units with self-loops, the outputs;
        # the predictions made before the last step are counted for the mean per sensor
        for a in range(lanes):
            low[a] = np.uint32(pkey[a] & low_mask)
        for j in range(hp):
            row = p_prefix[j]
            for a in range(lanes):
                acc[a] = row[low[a]]
            i = bits
            while i + 4 <= inputs:  # four inputs per pass over the agents, added in order
                u0, u1, u2, u3 = p_u[g, 0, i], p_u[g, 0, i + 1], p_u[g, 0, i + 2], p_u[g, 0, i + 3]
                o0, o1, o2, o3 = p_u[g, 1, i], p_u[g, 1, i + 1], p_u[g, 1, i + 2], p_u[g, 1, i + 3]
                w0, w1 = p_hidden[g, j, i], p_hidden[g, j, i + 1]
                w2, w3 = p_hidden[g, j, i + 2], p_hidden[g, j, i + 3]
                y0, y1, y2, y3 = u0 * w0, u1 * w1, u2 * w2, u3 * w3
                x0, x1, x2, x3 = o0 * w0, o1 * w1, o2 * w2, o3 * w3
                b0 = np.int32(1) << np.int32(i)
                b1, b2, b3 = b0 << 1, b0 << 2, b0 << 3
                for a in range(lanes):
                    k = pkey[a]
                    acc[a] = (
                        acc[a]
                        + (x0 if k & b0 else y0)
                        + (x1 if k & b1 else y1)
                        + (x2 if k & b2 else y2)
                        + (x3 if k & b3 else y3)
                    )
                i += 4
            while i < inputs:
                y0 = p_u[g, 0, i] * p_hidden[g, j, i]
                x0 = p_u[g, 1, i] * p_hidden[g, j, i]
                b0 = np.int32(1) << np.int32(i)
                for a in range(lanes):
                    acc[a] += x0 if pkey[a] & b0 else y0
                i += 1
            v = p_self[g, j]
            if exact:
                for a in range(lanes):
                    hidden[j, a] = c_activation(acc[a] + hidden[j, a] * v)
            else:
                for a in range(lanes):
                    hidden[j, a] = tanh_fast(acc[a] + hidden[j, a] * v)
        if o > 0:
            for a in range(lanes):
                pmask[a] = first
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
                w, w1 = p_out[g, q, j], p_out[g, q, j + 1]
                x, x1 = p_out[g, qa, j], p_out[g, qa, j + 1]
                y, y1 = p_out[g, qb, j], p_out[g, qb, j + 1]
                z, z1 = p_out[g, qc, j], p_out[g, qc, j + 1]
                for a in range(lanes):
                    h, h1 = hidden[j, a], hidden[j + 1, a]
                    acc[a] = acc[a] + h * w + h1 * w1
                    acc2[a] = acc2[a] + h * x + h1 * x1
                    acc3[a] = acc3[a] + h * y + h1 * y1
                    acc4[a] = acc4[a] + h * z + h1 * z1
            if hp % 2 == 1:
                w, x = p_out[g, q, hp - 1], p_out[g, qa, hp - 1]
                y, z = p_out[g, qb, hp - 1], p_out[g, qc, hp - 1]
                for a in range(lanes):
                    h = hidden[hp - 1, a]
                    acc[a] += h * w
                    acc2[a] += h * x
                    acc3[a] += h * y
                    acc4[a] += h * z
            _read_outputs(acc, outputs[q], q, pmask, ones)
            if qa != q:
                _read_outputs(acc2, outputs[qa], qa, pmask, ones)
            if qb != qa:
                _read_outputs(acc3, outputs[qb], qb, pmask, ones)
            if qc != qb:
                _read_outputs(acc4, outputs[qc], qc, pmask, ones)
        # moves in index order against the snapshot and the cells taken so far this step
        now = 2 * (t + 1)
        for rep in range(reps):
            event_r = event[rep]
            lines_r = lines[rep]
            for a in range(np.uint64(rep * n), np.uint64(rep * n + n)):
                c = cell[a]
                h = head[a]
                # a turn adds 1 (left) or 3 (right) to the heading, a move or a block adds 0
                head[a] = (h + a0[a] * (3 - 2 * left[a])) & 3
                front = front_of[c * np.uint32(4) + h]
                e = event_r[front]
                if (a0[a] == 0) & (e < now) & (e & 1 == 0):
                    event_r[front] = now + 1
                    event_r[c] = now
                    cell[a] = front
                    # the mover's bits leave its cell's row and column for the front cell's
                    lines_r[row_of[c]] ^= row_bits[c]
                    lines_r[col_of[c]] ^= col_bits[c]
                    lines_r[row_of[front]] ^= row_bits[front]
                    lines_r[col_of[front]] ^= col_bits[front]
    for q in range(o):  # the last step's predictions are never scored
        for a in range(lanes):
            ones[q, a] -= (pmask[a] >> outputs[q]) & 1
    for rep in range(reps):
        for q in range(o):
            total = 0
            for a in range(rep * n, rep * n + n):
                total += ones[q, a]
            counts[rep, outputs[q]] = total
        for a in range(n):
            final[rep, a, 0] = cell[rep * n + a]
            final[rep, a, 1] = head[rep * n + a]
        for k in range(r):
            if learned[k]:  # the first step's prediction, then those made before the last
                predsum[rep, k] = counts[rep, k] + fixed[k] * n
            else:
                predsum[rep, k] = fixed[k] * n * steps
    if trace_rep >= 0:
        for a in range(n):
            trace[steps, a, 0] = cell[trace_rep * n + a]
            trace[steps, a, 1] = head[trace_rep * n + a]


@kernel
def final_sensors(nb: np.ndarray, state: np.ndarray, out: np.ndarray) -> None:
    """Mean over agents of each true sensor value in configuration ``state`` ((N, 2)) into
    ``out`` (R,): the behaviour characterisation's per-run part."""
    cells, r = nb.shape[0], nb.shape[2]
    n = state.shape[0]
    occ = np.zeros(cells, dtype=np.uint8)
    for a in range(n):
        occ[state[a, 0]] = 1
    for k in range(r):
        total = 0
        for a in range(n):
            total += occ[nb[state[a, 0], state[a, 1], k]]
        out[k] = total / n


@kernel
def evaluate_batch(
    nb: np.ndarray,
    window: np.ndarray,
    width: int,
    starts: np.ndarray,
    steps: int,
    a_u: np.ndarray,
    a_hidden: np.ndarray,
    a_out: np.ndarray,
    p_u: np.ndarray,
    p_hidden: np.ndarray,
    p_self: np.ndarray,
    p_out: np.ndarray,
    outputs: np.ndarray,
    fixed: np.ndarray,
    noise_threshold: int,
    noise_key: int,
    exact: bool,
    fitness: np.ndarray,
    predmean: np.ndarray,
    final: np.ndarray,
    behaviour: np.ndarray,
    trace: np.ndarray,
    trace_run: int,
) -> None:
    """Every genome of the batch on every start configuration (``starts``: (reps, N, 2)).

    Writes, per genome g and run r: ``fitness[g, r]`` (share of correct predictions, Eq. 1),
    ``predmean[g, r, k]`` (mean scored prediction of sensor k), ``final[g, r]`` (poses after the
    last step) and ``behaviour[g, r, k]`` (mean true sensor value over agents in that final
    configuration). The run ``g * reps + r == trace_run`` is recorded into ``trace``.
    """
    genomes = a_u.shape[0]
    reps, n = starts.shape[0], starts.shape[1]
    r = nb.shape[2]
    tables = world_tables(nb, width, window.shape[0] > 0)
    memo = np.empty(1 << (r + 1), dtype=np.int8)
    correct = np.empty(reps, dtype=np.int64)
    predsum = np.empty((reps, r), dtype=np.float64)
    for g in range(genomes):
        memo[:] = -1
        trace_rep = trace_run - g * reps if g * reps <= trace_run < (g + 1) * reps else -1
        simulate_genome(
            nb, window, width, tables, starts, steps, g, a_u, a_hidden, a_out, p_u, p_hidden,
            p_self, p_out, outputs, fixed, memo, noise_threshold, noise_key, exact, correct,
            predsum, final[g], trace, trace_rep,
        )  # fmt: skip
        for rep in range(reps):
            fitness[g, rep] = correct[rep] / (steps * n * r)
            for k in range(r):
                predmean[g, rep, k] = predsum[rep, k] / (steps * n)
            final_sensors(nb, final[g, rep], behaviour[g, rep])
