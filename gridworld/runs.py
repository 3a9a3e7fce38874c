"""Compiled runs of the grid world: whole generations in one call (:func:`evaluate_batch`).

One run of one genome from one start configuration goes as the authors' code does it. Each step
t = 0 ... T-1: (1) the occupancy of the start of the step is the snapshot every agent senses;
(2) for each agent in index order its sensors are read, last step's prediction is scored against
them, the actor decides, the predictor predicts the next reading, and its new pose is computed: a
forward move succeeds only if the front cell is empty in the snapshot and no agent of lower index
has moved into it during this step (so conflicts go to the lower index and nobody enters a cell
being vacated), a turn always succeeds; (3) all agents take their new poses.

Sensing is synchronous, so the networks of all agents of a step are computed together (the
predictor in vectors across agents, :mod:`gridworld.predictor`); only the moves are resolved one
agent after the other. Both networks take their hidden units' input sums from a per-genome table
of the sums over all inputs for every pattern of their bits (the actor's by unit,
:func:`gridworld.kernels.prefix_sums`; the predictor's by pattern,
:func:`gridworld.predictor.input_sums`): the code's float32 operations, so its sums bit for bit,
at a fraction of the work. The actor has no state: its decision is a function of the R + 1 input
bits, computed for every input before a genome's runs and looked up in them
(:func:`gridworld.kernels.actor_decisions`); it is computed with a fast tanh and computed again
with the code's tanh only when an output lies too near zero for the fast one to decide its sign,
so the decision is the code's. The predictor's hidden units use
:func:`gridworld.kernels.tanh_fast` (a rational approximation good to float32 rounding) unless
``exact`` asks for the code's exp-based tanh: trajectories never depend on it, only the rare
prediction whose output lies within float32 rounding of zero can.

Sensor noise flips each sensor value an agent reads with probability ``noise`` (independent per
run, step, agent and sensor; the same flips for every genome given the same ``noise_key``). The
noisy values go into both networks and the fitness; moves are blocked by true occupancy only.

:func:`simulate_genome` runs a genome's runs side by side as a loop of named steps, each over all
agents of all runs: ``_sense`` (with the noise), ``_score``, ``_act``,
:func:`gridworld.predictor.predict`, ``_move``; they share the agents' poses and decisions
(:class:`Agents`), the runs' occupancy (:class:`Occupancy`) and the genome's networks (its
actor's decisions, :class:`gridworld.predictor.Predictor`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from gridworld.kernels import Noise, Torus, WorldTables, actor_decisions, noise_bits
from gridworld.predictor import LANE_ALIGN, make_predictor, predict
from gridworld.simd import UNITS
from minimize_surprise.gridnet import GridNetworks
from minimize_surprise.jit import kernel

__all__ = ["BatchOutcome", "Room", "RunOutcome", "evaluate_batch", "new_room", "simulate_genome"]


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


class Agents(NamedTuple):
    """The agents of all runs of one genome side by side (lane ``rep * N + a`` is agent a of run
    rep): the pose (``cell``, ``head``) and the actor's last decision (``a0`` 1: turn, then
    ``left`` 1: to the left, 0: to the right)."""

    cell: np.ndarray
    head: np.ndarray
    a0: np.ndarray
    left: np.ndarray


class Occupancy(NamedTuple):
    """Each run's occupancy, twice. ``event`` (reps, cells): each cell's last event, 2 * time + 1
    when an agent entered it (or stood on it at the start, time 0), 2 * time when it was left,
    with time t + 1 for step t. A cell is occupied at the start of a step if its last event is an
    entry, and taken or being left this step if its last event is this step's: one load decides a
    forward move. ``lines`` (reps, H + W): the occupancy as bit lines (rows by y, then columns by
    x; see :func:`gridworld.kernels.world_tables`), what the sensors read."""

    event: np.ndarray
    lines: np.ndarray


class Room(NamedTuple):
    """Working space a batch reuses from genome to genome (fresh arrays of a few megabytes per
    genome would be faulted in again each time): ``memo`` (2^I,) int8 the actor's decisions by
    input bits, ``sums`` (H_a, 2^I) and ``z`` (2, 2^I) room to compute them
    (:func:`gridworld.kernels.actor_decisions`), ``table`` (2^I, 16) the predictor's input sums
    (:func:`gridworld.predictor.make_predictor`)."""

    memo: np.ndarray
    sums: np.ndarray
    z: np.ndarray
    table: np.ndarray


@kernel
def new_room(nets: GridNetworks, sensors: int) -> Room:
    """A :class:`Room` for genomes of ``nets`` with ``sensors`` sensors."""
    patterns = 1 << (sensors + 1)
    return Room(
        np.empty(patterns, dtype=np.int8),
        np.empty((nets.a_hidden.shape[1], patterns), dtype=np.float32),
        np.empty((2, patterns), dtype=np.float32),
        np.empty((patterns, UNITS), dtype=np.float32),
    )


# The steps of a run (simulate_genome's loop, each called once per time step) take structures
# they read (nearly) all of, and plain arrays, and read the fields into locals at their top: a
# compiled call costs about a nanosecond for each array of its arguments it does not use (passed
# the batch-wide GridNetworks and one structure of every lane array, the steps made a generation
# without a predictor 8% slower). The structures are made once per genome.


@kernel
def _place_agents(torus: Torus, starts: np.ndarray) -> tuple[Agents, Occupancy]:
    """The agents on their ``starts`` ((reps, N, 2): cell, heading) and the runs' occupancy."""
    nb, width, tables = torus.nb, torus.width, torus.tables
    row_of, col_of, row_bits, col_bits = (
        tables.row_of,
        tables.col_of,
        tables.row_bits,
        tables.col_bits,
    )
    cells = nb.shape[0]
    reps, n = starts.shape[0], starts.shape[1]
    lanes = reps * n
    cell = np.empty(lanes, dtype=np.uint32)
    head = np.empty(lanes, dtype=np.uint32)
    for rep in range(reps):
        for a in range(n):
            cell[rep * n + a] = starts[rep, a, 0]
            head[rep * n + a] = starts[rep, a, 1]
    event = np.zeros((reps, cells), dtype=np.int32)
    lines = np.zeros((reps, cells // width + width), dtype=np.uint64)
    for rep in range(reps):
        for a in range(rep * n, rep * n + n):
            c = cell[a]
            event[rep, c] = 1
            lines[rep, row_of[c]] |= row_bits[c]
            lines[rep, col_of[c]] |= col_bits[c]
    a0 = np.zeros(lanes, dtype=np.int64)
    left = np.zeros(lanes, dtype=np.int64)
    return Agents(cell, head, a0, left), Occupancy(event, lines)


@kernel
def _record(trace: np.ndarray, t: int, agents: Agents, rep: int) -> None:
    """Run rep's poses into ``trace[t]``."""
    cell, head = agents.cell, agents.head
    n = trace.shape[1]
    for a in range(n):
        trace[t, a, 0] = cell[rep * n + a]
        trace[t, a, 1] = head[rep * n + a]


@kernel
def _sense(
    torus: Torus,
    noise: Noise,
    agents: Agents,
    occupancy: Occupancy,
    key: np.ndarray,
    base: np.ndarray,
    flips: np.ndarray,
    t: int,
    steps: int,
) -> None:
    """Step t's sensor bits of every agent into ``key``, read on its run's snapshot: three 5-bit
    windows of the run's bit lines per agent with a ``torus.window``, else sensor by sensor
    (``base``: room per lane); then the noise's flips (``flips``: room for one run's)."""
    nb, window, tables = torus.nb, torus.window, torus.tables
    sense = tables.sense
    noise_threshold, noise_key = noise
    cell, head = agents.cell, agents.head
    event, lines = occupancy
    reps, r = event.shape[0], nb.shape[2]
    n = key.shape[0] // reps
    five = np.uint64(31)
    low16 = np.uint64(0xFFFF)
    sixteen, sixteen2, sixteen3 = np.uint64(16), np.uint64(32), np.uint64(48)
    for rep in range(reps):
        lo, hi = rep * n, rep * n + n
        if window.shape[0] > 0:
            lines_r = lines[rep]
            for a in range(np.uint64(lo), np.uint64(hi)):
                d = head[a]
                i = np.uint32(2) * cell[a] + (d & np.uint32(1))
                packed = sense[i]
                s0 = packed >> sixteen3
                w0 = (lines_r[packed & low16] >> s0) & five
                w1 = (lines_r[(packed >> sixteen) & low16] >> s0) & five
                w2 = (lines_r[(packed >> sixteen2) & low16] >> s0) & five
                key[a] = window[d, 0, w0] | window[d, 1, w1] | window[d, 2, w2]
        else:
            event_r = event[rep]
            nbf = nb.ravel()
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


#: Lanes _score counts in one go: its byte counters hold up to 255.
_SCORE_CHUNK = 255
#: Times a 7-bit value, spreads bit k to bit 8 k (the copies shifted by 7 k never overlap) ...
_SPREAD = np.uint64(0x0002040810204081)
#: ... where this mask keeps it: a byte per bit, summed over lanes without carries.
_BYTE_LOWS = np.uint64(0x0101010101010101)


@kernel(inline=True)
def _bytes_of(bits: np.uint64) -> np.uint64:
    # Bits 0..6 of bits, one per byte (bit k to byte k).
    return ((bits & np.uint64(0x7F)) * _SPREAD) & _BYTE_LOWS


@kernel
def _score(
    key: np.ndarray, pmask: np.ndarray, r: int, correct: np.ndarray, predsum: np.ndarray
) -> None:
    """Adds to ``correct[rep]`` how many of the R sensor bits of run rep's agents (``key``) last
    step's predictions (``pmask``) got right, and to ``predsum[rep, k]`` (float64, exact for
    such counts) how many of them predicted sensor k as 1. Bit k of every lane goes to byte k
    of a counter (two counters per sum, the sensors 0-6 and 7-13: R is at most 14), so one pass
    of a few integer operations per lane, which vectorises, counts every sensor at once."""
    reps = correct.shape[0]
    n = key.shape[0] // reps
    seven = np.uint64(7)
    for rep in range(reps):
        wrong = np.int64(0)
        for start in range(rep * n, rep * n + n, _SCORE_CHUNK):
            stop = min(start + _SCORE_CHUNK, rep * n + n)
            wrong_low, wrong_high = np.uint64(0), np.uint64(0)
            ones_low, ones_high = np.uint64(0), np.uint64(0)
            for a in range(np.uint64(start), np.uint64(stop)):
                m = np.uint64(pmask[a])
                x = np.uint64(key[a]) ^ m
                wrong_low += _bytes_of(x)
                wrong_high += _bytes_of(x >> seven)
                ones_low += _bytes_of(m)
                ones_high += _bytes_of(m >> seven)
            for k in range(7):
                shift = np.uint64(8 * k)
                wrong += np.int64((wrong_low >> shift) & np.uint64(255))
                wrong += np.int64((wrong_high >> shift) & np.uint64(255))
                if k < r:
                    predsum[rep, k] += np.float64((ones_low >> shift) & np.uint64(255))
                if k + 7 < r:
                    predsum[rep, k + 7] += np.float64((ones_high >> shift) & np.uint64(255))
        correct[rep] += n * r - wrong


@kernel
def _act(memo: np.ndarray, agents: Agents, key: np.ndarray, pkey: np.ndarray, r: int) -> None:
    """The actor's decisions (``memo``, by input bits) for every lane's sensor bits (``key``) and
    last a0, into ``agents.a0`` and ``agents.left``, and the predictor's inputs (``pkey``: ``key``
    with the new a0 above it)."""
    a0, left = agents.a0, agents.left
    for a in range(key.shape[0]):
        # as int64: interpreted, an int8 shifted by r overflows
        m = np.int64(memo[np.uint64(key[a] | (a0[a] << r))])
        a0[a] = m & 1
        left[a] = m >> 1
        pkey[a] = np.int32(key[a] | ((m & 1) << r))


@kernel
def _move(tables: WorldTables, agents: Agents, occupancy: Occupancy, t: int) -> None:
    """Step t's moves, run by run and in index order, against the run's snapshot and the cells
    taken so far this step; turns always succeed."""
    front_of, row_of, col_of = tables.front_of, tables.row_of, tables.col_of
    row_bits, col_bits = tables.row_bits, tables.col_bits
    cell, head, a0, left = agents
    event, lines = occupancy
    reps = event.shape[0]
    n = cell.shape[0] // reps
    now = 2 * (t + 1)
    for rep in range(reps):
        event_r = event[rep]
        lines_r = lines[rep]
        lo = rep * n
        for a in range(np.uint64(lo), np.uint64(lo + n)):
            c = cell[a]
            h = head[a]
            # a turn adds 1 (left) or 3 (right) to the heading, a move or a block adds 0
            head[a] = (h + a0[a] * (3 - 2 * left[a])) & 3
            front = front_of[c * np.uint32(4) + h]
            e = event_r[front]
            # one branch, not three (LLVM makes a branch of each comparison in an &, and a move
            # is as likely as not): an agent goes when its a0 is 0 (a move) and the front
            # cell's last event is older than this step (the sign of e - now) and a leaving (e
            # even)
            stay = a0[a] | (e & 1) | ((((e - now) >> 63) & 1) ^ 1)
            if stay == 0:
                event_r[front] = now + 1
                event_r[c] = now
                cell[a] = front
                # the mover's bits leave its cell's row and column for the front cell's
                lines_r[row_of[c]] ^= row_bits[c]
                lines_r[col_of[c]] ^= col_bits[c]
                lines_r[row_of[front]] ^= row_bits[front]
                lines_r[col_of[front]] ^= col_bits[front]


@kernel
def _tally(agents: Agents, out: RunOutcome) -> None:
    """After the last step: each run's final poses."""
    cell, head = agents.cell, agents.head
    final = out.final
    reps, n = final.shape[0], final.shape[1]
    for rep in range(reps):
        for a in range(n):
            final[rep, a, 0] = cell[rep * n + a]
            final[rep, a, 1] = head[rep * n + a]


@kernel
def simulate_genome(
    torus: Torus,
    starts: np.ndarray,
    steps: int,
    nets: GridNetworks,
    g: int,
    room: Room,
    noise: Noise,
    exact: bool,
    out: RunOutcome,
) -> None:
    """Genome ``g`` of ``nets`` on every start configuration of ``starts`` ((reps, N, 2): cell,
    heading), the runs side by side so the networks work on reps x N agents at once; results
    into ``out`` (:class:`RunOutcome`), in working space ``room`` (:func:`new_room`): the actor's
    decisions for every input are computed first, then looked up. With a ``torus.window`` the
    sensors are read from bit rows and columns of the occupancy; without, cell by cell.
    """
    tables = torus.tables
    correct, predsum, trace, trace_rep = out.correct, out.predsum, out.trace, out.trace_rep
    reps, n, r = starts.shape[0], starts.shape[1], torus.nb.shape[2]
    lanes = reps * n
    agents, occupancy = _place_agents(torus, starts)
    memo = room.memo
    actor_decisions(nets.a_u, nets.a_hidden, nets.a_out, g, room.sums, room.z, memo)
    predictor = make_predictor(nets, g, exact, room.table)
    # per lane: the sensor bits read this step; the predictor's inputs (those bits with this
    # step's a0 above them), its hidden state (a row, units beyond H_p 0: gridworld.predictor)
    # and the bits of its prediction to be scored at the next step, the predictor's lanes
    # padded (gridworld.predictor.LANE_ALIGN)
    padded = -(-lanes // LANE_ALIGN) * LANE_ALIGN
    key = np.zeros(lanes, dtype=np.int64)
    pkey = np.zeros(padded, dtype=np.int32)
    hidden = np.zeros((padded, UNITS), dtype=np.float32)
    pmask = np.full(padded, predictor.first, dtype=np.uint32)
    base = np.zeros(lanes, dtype=np.int64)
    flips = np.zeros(n * r, dtype=np.uint8)
    correct[:] = 0
    predsum[:] = 0.0  # per run and sensor: how many scored predictions said 1
    for t in range(steps):
        if trace_rep >= 0:
            _record(trace, t, agents, trace_rep)
        _sense(torus, noise, agents, occupancy, key, base, flips, t, steps)
        _score(key, pmask, r, correct, predsum)
        _act(memo, agents, key, pkey, r)
        if predictor.keep != 0:  # without outputs every prediction is fixed
            predict(predictor, pkey, hidden, pmask)
        _move(tables, agents, occupancy, t)
    _tally(agents, out)
    if trace_rep >= 0:
        _record(trace, steps, agents, trace_rep)


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
    torus: Torus,
    starts: np.ndarray,
    steps: int,
    nets: GridNetworks,
    noise: Noise,
    exact: bool,
    out: BatchOutcome,
) -> None:
    """Every genome of ``nets`` on every start configuration (``starts``: (reps, N, 2)) in
    ``torus`` (:func:`build_torus`).

    Writes into ``out`` (:class:`BatchOutcome`), per genome g and run r: ``fitness[g, r]`` (share
    of correct predictions, Eq. 1), ``predmean[g, r, k]`` (mean scored prediction of sensor k),
    ``final[g, r]`` (poses after the last step) and ``behaviour[g, r, k]`` (mean true sensor value
    over agents in that final configuration); the run ``g * reps + r == out.trace_run`` is
    recorded into ``out.trace``.
    """
    fitness, predmean, final, behaviour, trace, trace_run = out
    nb = torus.nb
    genomes = nets.a_u.shape[0]
    reps, n = starts.shape[0], starts.shape[1]
    r = nb.shape[2]
    room = new_room(nets, r)
    correct = np.empty(reps, dtype=np.int64)
    predsum = np.empty((reps, r), dtype=np.float64)
    for g in range(genomes):
        trace_rep = trace_run - g * reps if g * reps <= trace_run < (g + 1) * reps else -1
        run = RunOutcome(correct, predsum, final[g], trace, trace_rep)
        simulate_genome(torus, starts, steps, nets, g, room, noise, exact, run)
        for rep in range(reps):
            fitness[g, rep] = correct[rep] / (steps * n * r)
            for k in range(r):
                predmean[g, rep, k] = predsum[rep, k] / (steps * n)
            final_sensors(nb, final[g, rep], behaviour[g, rep])
