"""Compiled runs of the grid world: whole generations in one call (:func:`evaluate_batch`).

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

from typing import NamedTuple

import numpy as np

from gridworld.kernels import (
    PREFIX_BITS,
    Noise,
    Torus,
    WorldTables,
    actor_decision,
    noise_bits,
    prefix_sums,
    read_outputs,
    tanh_fast,
    world_tables,
)
from minimize_surprise.gridnet import GridNetworks, c_activation
from minimize_surprise.jit import kernel

__all__ = ["BatchOutcome", "RunOutcome", "evaluate_batch", "simulate_genome"]


class RunOutcome(NamedTuple):
    """What :func:`simulate_genome` writes per run ``rep`` of one genome: ``correct[rep]`` the
    correct predictions, ``predsum[rep]`` (R,) the scored predictions summed over steps and
    agents, ``final[rep]`` (N, 2) the poses after the last step; run ``trace_rep`` (-1: none)
    has its poses before every step and after the last written to ``trace`` ((T + 1, N, 2))."""

    correct: np.ndarray
    predsum: np.ndarray
    final: np.ndarray
    trace: np.ndarray
    trace_rep: int


class BatchOutcome(NamedTuple):
    """What :func:`evaluate_batch` writes per genome g and run r: ``fitness[g, r]``,
    ``predmean[g, r, k]``, ``final[g, r]``, ``behaviour[g, r, k]``; the run
    ``g * reps + r == trace_run`` (-1: none) is recorded into ``trace``."""

    fitness: np.ndarray
    predmean: np.ndarray
    final: np.ndarray
    behaviour: np.ndarray
    trace: np.ndarray
    trace_run: int


@kernel
def _move_run(
    tables: WorldTables,
    cell: np.ndarray,
    head: np.ndarray,
    a0: np.ndarray,
    left: np.ndarray,
    event_r: np.ndarray,
    lines_r: np.ndarray,
    lo: int,
    n: int,
    t: int,
) -> None:
    """Step t's moves of the agents ``lo`` ... ``lo + n - 1`` of one run, in index order, against
    the snapshot and the cells taken so far this step (``event_r``, ``lines_r``: the run's)."""
    front_of, row_of, col_of = tables.front_of, tables.row_of, tables.col_of
    row_bits, col_bits = tables.row_bits, tables.col_bits
    now = 2 * (t + 1)
    for a in range(np.uint64(lo), np.uint64(lo + n)):
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


@kernel
def _tally(
    nets: GridNetworks,
    ones: np.ndarray,
    pmask: np.ndarray,
    cell: np.ndarray,
    head: np.ndarray,
    steps: int,
    n: int,
    out: RunOutcome,
) -> None:
    """After the last step: each run's final poses and its scored predictions per sensor (the
    first step's fixed one, then those made before the last step; ``ones`` counts every
    prediction of 1 made, ``pmask`` holds the last step's, never scored)."""
    outputs, fixed = nets.outputs, nets.fixed
    predsum, final = out.predsum, out.final
    reps, r, o = final.shape[0], fixed.shape[0], outputs.shape[0]
    lanes = reps * n
    for q in range(o):
        for a in range(lanes):
            ones[q, a] -= (pmask[a] >> outputs[q]) & 1
    learned = np.zeros(r, dtype=np.bool_)
    for q in range(o):
        learned[outputs[q]] = True
    counts = np.zeros((reps, r), dtype=np.int64)
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
            if learned[k]:
                predsum[rep, k] = counts[rep, k] + fixed[k] * n
            else:
                predsum[rep, k] = fixed[k] * n * steps


@kernel(error_model="numpy")
def simulate_genome(
    torus: Torus,
    starts: np.ndarray,
    steps: int,
    nets: GridNetworks,
    g: int,
    memo: np.ndarray,
    noise: Noise,
    exact: bool,
    out: RunOutcome,
) -> None:
    """Genome ``g`` of ``nets`` on every start configuration of ``starts`` ((reps, N, 2): cell,
    heading), the runs side by side so the networks work on reps x N agents at once; results
    into ``out`` (:class:`RunOutcome`). ``memo`` caches the actor's decisions by input bits (-1:
    not yet known). With a ``window`` the sensors are read from bit rows and columns of the
    occupancy; without, cell by cell.
    """
    nb, window, width, tables = torus
    a_u, a_hidden, a_out = nets.a_u, nets.a_hidden, nets.a_out
    p_u, p_hidden, p_self, p_out = nets.p_u, nets.p_hidden, nets.p_self, nets.p_out
    outputs, fixed = nets.outputs, nets.fixed
    noise_threshold, noise_key = noise
    correct, trace, trace_rep = out.correct, out.trace, out.trace_rep
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
    sense_line, sense_shift, popcount = tables.sense_line, tables.sense_shift, tables.popcount
    row_of, col_of, row_bits, col_bits = (
        tables.row_of,
        tables.col_of,
        tables.row_bits,
        tables.col_bits,
    )
    five = np.uint64(31)
    first = np.int64(0)
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
    # per output and agent: how many of its predictions said 1
    ones = np.zeros((max(o, 1), lanes), dtype=np.int32)
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
                    flips[m] = noise_bits(noise_key, origin + m) < noise_threshold
                for a in range(lo, hi):
                    flipped = np.int64(0)
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
            read_outputs(acc, outputs[q], q, pmask, ones)
            if qa != q:
                read_outputs(acc2, outputs[qa], qa, pmask, ones)
            if qb != qa:
                read_outputs(acc3, outputs[qb], qb, pmask, ones)
            if qc != qb:
                read_outputs(acc4, outputs[qc], qc, pmask, ones)
        # moves in index order against the snapshot and the cells taken so far this step
        for rep in range(reps):
            _move_run(tables, cell, head, a0, left, event[rep], lines[rep], rep * n, n, t)
    _tally(nets, ones, pmask, cell, head, steps, n, out)
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
    nets: GridNetworks,
    noise: Noise,
    exact: bool,
    out: BatchOutcome,
) -> None:
    """Every genome of ``nets`` on every start configuration (``starts``: (reps, N, 2)).

    Writes into ``out`` (:class:`BatchOutcome`), per genome g and run r: ``fitness[g, r]`` (share
    of correct predictions, Eq. 1), ``predmean[g, r, k]`` (mean scored prediction of sensor k),
    ``final[g, r]`` (poses after the last step) and ``behaviour[g, r, k]`` (mean true sensor value
    over agents in that final configuration); the run ``g * reps + r == out.trace_run`` is
    recorded into ``out.trace``.
    """
    fitness, predmean, final, behaviour, trace, trace_run = out
    genomes = nets.a_u.shape[0]
    reps, n = starts.shape[0], starts.shape[1]
    r = nb.shape[2]
    torus = Torus(nb, window, width, world_tables(nb, width, window.shape[0] > 0))
    memo = np.empty(1 << (r + 1), dtype=np.int8)
    correct = np.empty(reps, dtype=np.int64)
    predsum = np.empty((reps, r), dtype=np.float64)
    for g in range(genomes):
        memo[:] = -1
        trace_rep = trace_run - g * reps if g * reps <= trace_run < (g + 1) * reps else -1
        run = RunOutcome(correct, predsum, final[g], trace, trace_rep)
        simulate_genome(torus, starts, steps, nets, g, memo, noise, exact, run)
        for rep in range(reps):
            fitness[g, rep] = correct[rep] / (steps * n * r)
            for k in range(r):
                predmean[g, rep, k] = predsum[rep, k] / (steps * n)
            final_sensors(nb, final[g, rep], behaviour[g, rep])
