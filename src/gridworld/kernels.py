"""Compiled simulation of the grid world: whole generations in one call.

One run of one genome from one start configuration goes as the authors' code does it. Each step
t = 0 ... T-1: (1) the occupancy of the start of the step is the snapshot every agent senses;
(2) for each agent in index order its sensors are read, last step's prediction is scored against
them, the actor decides, the predictor predicts the next reading, and its new pose is computed: a
forward move succeeds only if the front cell is empty in the snapshot and no agent of lower index
has moved into it during this step (so conflicts go to the lower index and nobody enters a cell
being vacated), a turn always succeeds; (3) all agents take their new poses.

Sensing is synchronous, so the networks of all agents of a step are computed together (the
predictor vectorised across agents); only the moves are resolved one agent after the other. The
actor has no state: its decision is a function of the R + 1 input bits, computed by the code's
arithmetic the first time a genome meets an input and looked up afterwards. The predictor's hidden
units use :func:`tanh_fast` (a rational approximation good to float32 rounding) unless ``exact``
asks for the code's exp-based tanh: trajectories never depend on it, only the rare prediction
whose output lies within float32 rounding of zero can.

Sensor noise flips each sensor value an agent reads with probability ``noise`` (independent per
run, step, agent and sensor; the same flips for every genome given the same ``noise_key``). The
noisy values go into both networks and the fitness; moves are blocked by true occupancy only.
"""

from __future__ import annotations

import numpy as np

from surprise.gridnet import c_activation, c_negative
from surprise.jit import kernel
from surprise.rng import mix32

__all__ = ["actor_decision", "evaluate_batch", "tanh_fast"]


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
def actor_decision(
    a_u: np.ndarray,
    a_hidden: np.ndarray,
    a_out: np.ndarray,
    key: int,
    inputs: int,
    scratch: np.ndarray,
) -> int:
    """The actor's decision for the input bits in ``key`` (bit i = input i) by the code's
    arithmetic: a0 + 2 * (1 if it turns left). ``scratch`` holds at least H_a float32 values.

    Every hidden unit's sum runs over the inputs in order, in float32, as in the code; the
    units are summed side by side (inputs outer) so the loop vectorises across them.
    """
    ha = a_hidden.shape[0]
    for j in range(ha):
        scratch[j] = 0.0
    for i in range(inputs):
        u = a_u[(key >> i) & 1, i]
        for j in range(ha):
            scratch[j] += u * a_hidden[j, i]
    for j in range(ha):
        scratch[j] = c_activation(scratch[j])
    z0 = np.float32(0.0)
    z1 = np.float32(0.0)
    for j in range(ha):
        z0 += scratch[j] * a_out[0, j]
        z1 += scratch[j] * a_out[1, j]
    a0 = 0 if c_negative(z0) else 1
    left = 1 if c_negative(z1) else 0
    return a0 + 2 * left


@kernel
def _noise_bits(key: int, counter: int) -> int:
    # 32 random bits for one sensor reading, a pure function of the key and the reading's index.
    low = mix32(counter & 0xFFFFFFFF)
    high = mix32((counter >> 32) + 0x9E3779B9)
    return mix32(key ^ low ^ (high * 0x85EBCA6B))


@kernel
def _bitboards(
    cell: np.ndarray,
    lo: int,
    n: int,
    width: int,
    height: int,
    xof: np.ndarray,
    yof: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
) -> None:
    # Coordinates of agents lo ... lo + n - 1 and the doubled bit rows and columns they occupy.
    rows[:] = 0
    cols[:] = 0
    one = np.uint64(1)
    for a in range(lo, lo + n):
        x = xof[cell[a]]
        y = yof[cell[a]]
        xs[a] = x
        ys[a] = y
        rows[y] |= (one << np.uint64(x)) | (one << np.uint64(x + width))
        cols[x] |= (one << np.uint64(y)) | (one << np.uint64(y + height))


@kernel(error_model="numpy")
def simulate_genome(
    nb: np.ndarray,
    window: np.ndarray,
    width: int,
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
    the last written to ``trace`` ((T + 1, N, 2)). ``memo`` caches the actor's decisions by
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
    cell = np.empty(lanes, dtype=np.int32)
    head = np.empty(lanes, dtype=np.int32)
    for rep in range(reps):
        for a in range(n):
            cell[rep * n + a] = starts[rep, a, 0]
            head[rep * n + a] = starts[rep, a, 1]
    a0 = np.zeros(lanes, dtype=np.int64)
    left = np.zeros(lanes, dtype=np.int64)
    occ = np.zeros((reps, cells), dtype=np.uint8)
    claimed = np.zeros((reps, cells), dtype=np.int32)
    nbf = nb.ravel()
    # per agent: the sensor bits read this step with this step's a0 above them (the predictor's
    # inputs), and the bits of the prediction to be scored at the next step
    pkey = np.zeros(lanes, dtype=np.int32)
    scratch = np.zeros(a_hidden.shape[1], dtype=np.float32)
    key = np.zeros(lanes, dtype=np.int64)
    base = np.zeros(lanes, dtype=np.int64)
    # bit rows and columns of each run's occupancy, doubled (bits 0..W-1 repeated above) so a
    # window of 5 that wraps around is one shift; per-coordinate neighbour and shift tables
    bits_ok = window.shape[0] > 0
    height = cells // width
    rows = np.zeros((reps, height), dtype=np.uint64)
    cols = np.zeros((reps, width), dtype=np.uint64)
    xs = np.empty(lanes, dtype=np.int64)
    ys = np.empty(lanes, dtype=np.int64)
    xm = np.empty(width, dtype=np.int64)
    xp = np.empty(width, dtype=np.int64)
    sx = np.empty(width, dtype=np.uint64)
    ym = np.empty(height, dtype=np.int64)
    yp = np.empty(height, dtype=np.int64)
    sy = np.empty(height, dtype=np.uint64)
    for x in range(width):
        xm[x] = (x + width - 1) % width
        xp[x] = (x + 1) % width
        sx[x] = (x + width - 2) % width
    for y in range(height):
        ym[y] = (y + height - 1) % height
        yp[y] = (y + 1) % height
        sy[y] = (y + height - 2) % height
    five = np.uint64(31)
    xof = np.empty(cells, dtype=np.int64)
    yof = np.empty(cells, dtype=np.int64)
    front_of = np.empty(cells * 4, dtype=np.int64)
    for c in range(cells):
        xof[c] = c % width
        yof[c] = c // width
        for d in range(4):
            front_of[c * 4 + d] = nb[c, d, 0]
    before = np.empty(lanes, dtype=np.int32)
    first = 0
    for k in range(r):
        first |= np.int64(fixed[k]) << k
    pmask = np.full(lanes, first, dtype=np.int64)
    popcount = np.zeros(1 << r, dtype=np.uint8)
    for v in range(1, 1 << r):
        popcount[v] = popcount[v >> 1] + (v & 1)
    hidden = np.zeros((hp, lanes), dtype=np.float32)
    acc = np.empty(lanes, dtype=np.float32)
    acc2 = np.empty(lanes, dtype=np.float32)
    pre = np.empty((hp, lanes), dtype=np.float32)
    counts = np.zeros((reps, r), dtype=np.int64)
    learned = np.zeros(r, dtype=np.bool_)
    for q in range(o):
        learned[outputs[q]] = True
    for rep in range(reps):
        correct[rep] = 0
        for a in range(n):
            occ[rep, cell[rep * n + a]] = 1
        if bits_ok:
            _bitboards(cell, rep * n, n, width, height, xof, yof, xs, ys, rows[rep], cols[rep])
    for t in range(steps):
        if trace_rep >= 0:
            for a in range(n):
                trace[t, a, 0] = cell[trace_rep * n + a]
                trace[t, a, 1] = head[trace_rep * n + a]
        # sensing on each run's snapshot (sensor by sensor across the run's agents, so the
        # lookups vectorise), scoring last step's predictions
        for rep in range(reps):
            occ_r = occ[rep]
            lo, hi = rep * n, rep * n + n
            if bits_ok:
                for a in range(lo, hi):
                    x, y = xs[a], ys[a]
                    d = head[a]
                    if d & 1 == 0:
                        s0 = sx[x]
                        w0 = (rows[rep, ym[y]] >> s0) & five
                        w1 = (rows[rep, y] >> s0) & five
                        w2 = (rows[rep, yp[y]] >> s0) & five
                    else:
                        s0 = sy[y]
                        w0 = (cols[rep, xm[x]] >> s0) & five
                        w1 = (cols[rep, x] >> s0) & five
                        w2 = (cols[rep, xp[x]] >> s0) & five
                    key[a] = window[d, 0, w0] | window[d, 1, w1] | window[d, 2, w2]
            else:
                for a in range(lo, hi):
                    base[a] = (cell[a] * 4 + head[a]) * r
                    key[a] = 0
                for k in range(r):
                    for a in range(lo, hi):
                        key[a] |= np.int64(occ_r[nbf[base[a] + k]]) << k
            if noise_threshold > 0:
                for a in range(lo, hi):
                    for k in range(r):
                        counter = (((rep * steps) + t) * n + a - lo) * r + k
                        if _noise_bits(noise_key, counter) < noise_threshold:
                            key[a] ^= np.int64(1) << k
            wrong = 0
            for a in range(lo, hi):
                wrong += popcount[key[a] ^ pmask[a]]
            correct[rep] += n * r - wrong
        # the actor: its decision for these input bits, computed once per genome and input
        for a in range(lanes):
            full = key[a] | (a0[a] << r)
            m = memo[full]
            if m < 0:
                m = actor_decision(a_u[g], a_hidden[g], a_out[g], full, inputs, scratch)
                memo[full] = m
            a0[a] = m & 1
            left[a] = m >> 1
            pkey[a] = np.int32(key[a] | ((m & 1) << r))
        # predictor on all agents of all runs: hidden units with self-loops, then the outputs;
        # the predictions made before the last step are counted for the mean per sensor
        # input layer sums two hidden units at a time (sharing each agent's input bits)
        for j in range(0, hp - 1, 2):
            for a in range(lanes):
                acc[a] = 0.0
                acc2[a] = 0.0
            for i in range(inputs):
                c0 = p_u[g, 0, i] * p_hidden[g, j, i]
                c1 = p_u[g, 1, i] * p_hidden[g, j, i]
                d0 = p_u[g, 0, i] * p_hidden[g, j + 1, i]
                d1 = p_u[g, 1, i] * p_hidden[g, j + 1, i]
                bit = np.int32(1) << np.int32(i)
                for a in range(lanes):
                    on = pkey[a] & bit
                    acc[a] += c1 if on else c0
                    acc2[a] += d1 if on else d0
            for a in range(lanes):
                pre[j, a] = acc[a]
                pre[j + 1, a] = acc2[a]
        if hp % 2 == 1:
            j = hp - 1
            for a in range(lanes):
                acc[a] = 0.0
            for i in range(inputs):
                c0 = p_u[g, 0, i] * p_hidden[g, j, i]
                c1 = p_u[g, 1, i] * p_hidden[g, j, i]
                bit = np.int32(1) << np.int32(i)
                for a in range(lanes):
                    acc[a] += c1 if pkey[a] & bit else c0
            for a in range(lanes):
                pre[j, a] = acc[a]
        for j in range(hp):
            for a in range(lanes):
                acc[a] = pre[j, a]
            v = p_self[g, j]
            for a in range(lanes):
                acc[a] += hidden[j, a] * v
            if exact:
                for a in range(lanes):
                    hidden[j, a] = c_activation(acc[a])
            else:
                for a in range(lanes):
                    hidden[j, a] = tanh_fast(acc[a])
        if o > 0:
            for a in range(lanes):
                pmask[a] = first
        for q in range(o):
            for a in range(lanes):
                acc[a] = 0.0
            for j in range(hp):
                w = p_out[g, q, j]
                for a in range(lanes):
                    acc[a] += hidden[j, a] * w
            s = outputs[q]
            tiny = False
            for a in range(lanes):
                pmask[a] |= np.int64(acc[a] >= 0.0) << s
                tiny |= (acc[a] < 0.0) & (acc[a] > -1e-10)
            if tiny:  # where the code's tanh may round to 0, let it decide
                for a in range(lanes):
                    if not c_negative(acc[a]):
                        pmask[a] |= np.int64(1) << s
            if t < steps - 1:
                for rep in range(reps):
                    total = 0
                    for a in range(rep * n, rep * n + n):
                        total += (pmask[a] >> s) & 1
                    counts[rep, s] += total
        # moves in index order against the snapshot and the cells taken so far this step
        # (written without branches: whether an agent moves is not predictable)
        stamp = t + 1
        for rep in range(reps):
            occ_r = occ[rep]
            claimed_r = claimed[rep]
            for a in range(rep * n, rep * n + n):
                c = cell[a]
                h = head[a]
                before[a] = c
                front = front_of[c * 4 + h]
                moves = (a0[a] == 0) & (occ_r[front] == 0) & (claimed_r[front] != stamp)
                claimed_r[front] = stamp if moves else claimed_r[front]
                cell[a] = front if moves else c
                # a turn adds 1 (left) or 3 (right) to the heading, a move or a block adds 0
                head[a] = (h + a0[a] * (3 - 2 * left[a])) & 3
            for a in range(rep * n, rep * n + n):
                occ_r[before[a]] = 0
            for a in range(rep * n, rep * n + n):
                occ_r[cell[a]] = 1
            if bits_ok:
                _bitboards(cell, rep * n, n, width, height, xof, yof, xs, ys, rows[rep], cols[rep])
    for rep in range(reps):
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
    memo = np.empty(1 << (r + 1), dtype=np.int8)
    correct = np.empty(reps, dtype=np.int64)
    predsum = np.empty((reps, r), dtype=np.float64)
    for g in range(genomes):
        memo[:] = -1
        trace_rep = trace_run - g * reps if g * reps <= trace_run < (g + 1) * reps else -1
        simulate_genome(
            nb, window, width, starts, steps, g, a_u, a_hidden, a_out, p_u, p_hidden, p_self,
            p_out, outputs, fixed, memo, noise_threshold, noise_key, exact, correct, predsum,
            final[g], trace, trace_rep,
        )  # fmt: skip
        for rep in range(reps):
            fitness[g, rep] = correct[rep] / (steps * n * r)
            for k in range(r):
                predmean[g, rep, k] = predsum[rep, k] / (steps * n)
            final_sensors(nb, final[g, rep], behaviour[g, rep])
