"""Every robot's sensor values (:func:`sense`), in the order the world's sensors are configured.

IR from :mod:`.ir`; ground: ``ground_carpet`` over the carpet, ``ground_outside`` beyond its edge,
with Gaussian noise of ``ground_noise`` times the value; force as the step left it; light from a
lamp's fall-off or uniform. Then Gaussian ``noise`` on every value, clipped to [0, 1].
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from minimize_surprise.jit import borrow, kernel
from simulator.physics.grid import Cells, build, gather, grid_side, new_cells
from simulator.physics.ir import ir_noise, ir_readings
from simulator.physics.model import GROUND_POSITIONS, IR_POSITIONS, Sensing, gaussian

__all__ = ["SenseWork", "ir_reach", "sense", "sense_work"]


# Indices of the sensors in the full frame (minimize_surprise.sensors.ALL_SENSORS).
_IR0, _GROUND0, _FORCE, _LIGHT0 = 0, 7, 9, 10
#: Sensors in the full frame.
_FULL = 12
# Metres added to the IR's reach when picking the bodies a robot may see: rounding in the
# distances never drops one the sensors would see.
_REACH_SLACK = 1e-6


def ir_reach(robot_radius: float, body_offset: float, ir_range: float) -> float:
    """The farthest apart two body centres can be for one robot's IR to see the other: the
    IR's reach from a sensor (its range beyond the other body's radius) plus the farthest
    sensor from the body's centre (``Sensing.ir_reach``)."""
    far = max(
        math.hypot(IR_POSITIONS[k, 0] - body_offset, IR_POSITIONS[k, 1])
        for k in range(IR_POSITIONS.shape[0])
    )
    return ir_range + robot_radius + far


@kernel(inline=True)
def _within(
    bodies: np.ndarray, i: int, candidates: np.ndarray, m: int, reach: float, out: np.ndarray
) -> int:
    # The body centres of robots ``candidates[:m]`` but robot i closer than ``reach`` to robot
    # i's into the first rows of ``out``; their number. A robot's seven IR sensors then look at
    # these few instead of at every robot, and find the same nearest body.
    bx, by = bodies[i, 0], bodies[i, 1]
    reach2 = reach * reach
    kept = 0
    for q in range(m):
        j = candidates[q]
        dx = bodies[j, 0] - bx
        dy = bodies[j, 1] - by
        if j != i and dx * dx + dy * dy < reach2:
            out[kept, 0] = bodies[j, 0]
            out[kept, 1] = bodies[j, 1]
            kept += 1
    return kept


class SenseWork(NamedTuple):
    """The working arrays of :func:`sense` for N robots (:func:`sense_work`): ``full`` (N, 12)
    every sensor's value before the configured ones are picked; ``bodies`` and ``cos_sin`` (N,
    2) the body centres and the headings' cosines and sines; ``candidates`` (N) and ``near`` (N,
    2) the robots one robot's IR may see and the body centres of those in its reach. Held by the
    caller across steps: allocating them at every step cost more than a robot's sensing."""

    full: np.ndarray
    bodies: np.ndarray
    cos_sin: np.ndarray
    candidates: np.ndarray
    near: np.ndarray


def sense_work(robots: int) -> SenseWork:
    """Working arrays of :func:`sense` for ``robots`` robots."""
    return SenseWork(
        full=np.zeros((robots, _FULL)),
        bodies=np.empty((robots, 2)),
        cos_sin=np.empty((robots, 2)),
        candidates=np.empty(robots, dtype=np.int64),
        near=np.empty((robots, 2)),
    )


@kernel
def sense(
    sn: Sensing, pose: np.ndarray, force: np.ndarray, step: int, out: np.ndarray,
    work: SenseWork, grid: bool | None,
) -> None:  # fmt: skip
    """Every robot's sensor values for the arena as it is at ``step`` into ``out`` (N, R), in
    the order of ``sn.columns``; ``work`` the working arrays (:func:`sense_work`). From
    ``sn.grid_robots`` robots on, a robot's IR looks only at the robots in the cells of a grid
    around its own (.grid). ``grid`` None says the arena has fewer robots than that
    (:func:`~simulator.physics.grid.grid_choice`): numba then compiles only the all-pairs
    sensing, pruned by type."""
    n = pose.shape[0]
    if grid is None:
        _sense(sn, pose, force, step, out, work, None)
        return
    if sn.need_ir and n >= sn.grid_robots:
        side = grid_side(sn.wall_half, sn.ir_reach, n)
        if side > 1:
            _sense(sn, pose, force, step, out, work, new_cells(n, side))
            return
    _sense(sn, pose, force, step, out, work, None)


@kernel
def _sense(
    sn: Sensing, pose: np.ndarray, force: np.ndarray, step: int, out: np.ndarray,
    work: SenseWork, cells: Cells | None,
) -> None:  # fmt: skip
    # ``sense`` with every robot's IR looking at every other robot (``cells`` None) or at its
    # neighbours in the grid; numba compiles one of each, the choices on ``cells is None`` away.
    n = pose.shape[0]
    full, bodies, cos_sin, candidates, near = work
    # Each heading's cosine and sine once, for the bodies and the sensors.
    for i in range(n):
        c, s = math.cos(pose[i, 2]), math.sin(pose[i, 2])
        cos_sin[i, 0] = c
        cos_sin[i, 1] = s
        bodies[i, 0] = pose[i, 0] + sn.body_offset * c
        bodies[i, 1] = pose[i, 1] + sn.body_offset * s
    # With cells: the grid's arrays, read once and borrowed (jit.borrow; ``cells`` is an
    # argument, held by the caller): each call of ``gather`` would otherwise count a reference
    # on each of them, an atomic operation. ``candidates``: the robots a robot's IR may see
    # (every robot, or its neighbours in the grid); ``near``: the body centres of those within
    # its reach, in a row.
    reach = sn.ir_reach + _REACH_SLACK
    if cells is None:
        side, cell, start, order = 0, None, None, None
        for i in range(n):
            candidates[i] = i
    else:
        side, cell, start, order = borrow(cells)
        build(bodies[:, 0], bodies[:, 1], sn.wall_half, side, cell, start, order)
    for i in range(n):
        x, y = pose[i, 0], pose[i, 1]
        c, s = cos_sin[i, 0], cos_sin[i, 1]
        if sn.need_ir:
            m = n if cells is None else gather(i, side, cell, start, order, candidates, False)
            m = _within(bodies, i, candidates, m, reach, near)
            ir_readings(sn, near, m, x, y, c, s, full, i)
        if sn.need_ground:
            half_x, half_y = sn.arena_hx, sn.arena_hy
            for k in range(2):
                px, py = GROUND_POSITIONS[k, 0], GROUND_POSITIONS[k, 1]
                gx = x + c * px - s * py
                gy = y + s * px + c * py
                on = abs(gx) <= half_x and abs(gy) <= half_y
                full[i, _GROUND0 + k] = sn.ground_carpet if on else sn.ground_outside
        if sn.need_force:
            full[i, _FORCE] = force[i]
        if sn.need_light:
            for k in range(2):
                if sn.light:
                    px, py = sn.light_offsets[k, 0], sn.light_offsets[k, 1]
                    lx = x + c * px - s * py - sn.light_x
                    ly = y + s * px + c * py - sn.light_y
                    h2 = sn.lamp_h2
                    ratio = h2 / (h2 + lx * lx + ly * ly)
                    full[i, _LIGHT0 + k] = sn.light_centre * ratio**sn.light_exponent
                else:
                    full[i, _LIGHT0 + k] = sn.light_uniform
    _noise(sn, step, full, out)


@kernel(inline=True)
def _noise(sn: Sensing, step: int, full: np.ndarray, out: np.ndarray) -> None:
    # The readings' noise, in loops of their own after the readings: every draw is keyed by
    # (seed, step, robot, channel), so when it is drawn changes no value. In the readings' loop
    # the draws' branches kept numba from pruning about 16 reference counts per robot-step
    # (calls, if on arrays without an owner), more than the draws cost; here no loop hands an
    # array to anything.
    if sn.need_ir:
        ir_noise(sn, step, full)
    seed, columns = sn.seed, sn.columns
    if sn.need_ground and sn.ground_noise > 0.0:
        scale = sn.ground_noise
        for i in range(full.shape[0]):
            for k in range(2):
                value = full[i, _GROUND0 + k]
                if value > 0.0:
                    full[i, _GROUND0 + k] = value + scale * value * gaussian(seed, step, i, 48 + k)
    noise = sn.noise
    for i in range(full.shape[0]):
        for j in range(columns.shape[0]):
            value = full[i, columns[j]]
            if noise > 0.0:
                value += noise * gaussian(seed, step, i, j)
            out[i, j] = min(max(value, 0.0), 1.0)
