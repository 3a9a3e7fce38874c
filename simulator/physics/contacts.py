"""Contacts of robots with the walls and with each other.

A robot's body (and blade) is kept inside the walls; robots that overlap push each other apart,
half each, a blade against another robot's body included. Boxes are in :mod:`.boxes`.
"""

from __future__ import annotations

import math

import numpy as np

from minimize_surprise.jit import borrow, kernel
from simulator.physics.grid import Cells, build, gather, grid_side, mark_around, new_cells
from simulator.physics.model import Geometry

# Overlaps shallower than this (metres) are left alone: resolving them exactly would take many
# more passes for nothing anyone could measure (boxes and robots are a few centimetres).
_SLOP = 1e-5
# At most this many passes of robot-robot separation per step (most steps need none or one;
# pile-ups of several robots against a wall need more).
_ROBOT_PASSES = 8


@kernel
def _wall_shift(g: Geometry, x: float, y: float, c: float, s: float) -> tuple[float, float]:
    # Translation that brings a robot's body (and blade) back inside the walls.
    wx, wy = g.wall_hx, g.wall_hy
    r = g.robot_radius
    cx = x + g.body_offset * c
    cy = y + g.body_offset * s
    lo_x = r - wx - cx
    hi_x = cx - (wx - r)
    lo_y = r - wy - cy
    hi_y = cy - (wy - r)
    if g.blade:
        ax = x + g.blade_x * c - g.hw * s
        ay = y + g.blade_x * s + g.hw * c
        bx = ax + 2 * g.hw * s
        by = ay - 2 * g.hw * c
        tb = g.tb
        lo_x = max(lo_x, tb - wx - ax, tb - wx - bx)
        hi_x = max(hi_x, ax - (wx - tb), bx - (wx - tb))
        lo_y = max(lo_y, tb - wy - ay, tb - wy - by)
        hi_y = max(hi_y, ay - (wy - tb), by - (wy - tb))
    return max(lo_x, 0.0) - max(hi_x, 0.0), max(lo_y, 0.0) - max(hi_y, 0.0)


@kernel
def _keep_inside_walls(g: Geometry, pose: np.ndarray) -> None:
    for i in range(pose.shape[0]):
        c, s = math.cos(pose[i, 2]), math.sin(pose[i, 2])
        sx, sy = _wall_shift(g, pose[i, 0], pose[i, 1], c, s)
        pose[i, 0] += sx
        pose[i, 1] += sy


@kernel
def contact_reach(g: Geometry) -> float:
    """The farthest apart two body centres can be and still touch: the bodies' diameter, or a
    blade's reach (its far end from the body's centre, then the other body's radius and half
    the blade's thickness)."""
    reach = 2 * g.robot_radius
    if g.blade:
        reach = max(reach, math.hypot(g.blade_x - g.body_offset, g.hw) + g.robot_radius + g.tb)
    return reach


@kernel
def _separate_robots(g: Geometry, pose: np.ndarray, grid: bool | None) -> bool:
    # Whether any robot moved. From g.grid_robots robots on, a robot looks for the robots it
    # touches among its neighbours in a grid (.grid), below among every other robot; ``grid``
    # None (fewer robots: grid.grid_choice) compiles only the latter.
    n = pose.shape[0]
    if grid is not None and n >= g.grid_robots:
        side = grid_side(g.wall_half, contact_reach(g), n)
        if side > 1:
            cells = new_cells(n, side)
            touched = np.empty(n, dtype=np.bool_)
            hot = np.empty(side * side, dtype=np.bool_)
            return _separate(g, pose, cells, np.empty(n, dtype=np.int64), touched, hot)
    # No grid, no working arrays (an allocation per call would cost the small swarms).
    return _separate(g, pose, None, None, None, None)


@kernel(inline=True)
def _cold(cell: np.ndarray, hot: np.ndarray, i: int) -> bool:
    # Whether robot i is in a cold cell.
    return not hot[cell[i]]


@kernel
def _separate(
    g: Geometry, pose: np.ndarray, cells: Cells | None, near: np.ndarray, touched: np.ndarray,
    hot: np.ndarray,
) -> bool:  # fmt: skip
    # Each pass computes every push from the same positions, then applies them all, as a
    # simultaneous relaxation. A robot's pushes are added in increasing index of the other
    # robot: every other robot, or (``cells`` given) its neighbours in the grid, the same pushes
    # in the same order. Numba compiles one of each, the choices on ``cells is None`` away.
    #
    # With cells, a pass after the first looks only at the robots near one that the last pass
    # touched (docs/simulation.md, "Large swarms"): ``touched`` (N) the robots in an overlap,
    # pushed, or pushed off a wall, ``hot`` (side * side) the cells next to (or holding) a
    # touched robot where it is now. In a large swarm some pile-up somewhere takes every
    # pass; without this, each pass would cost as much as the first.
    n = pose.shape[0]
    moved = False
    # The six rows in one allocation.
    rows = np.empty((6, n))
    c, s, shift_x, shift_y, cx, cy = rows[0], rows[1], rows[2], rows[3], rows[4], rows[5]
    for i in range(n):
        c[i] = math.cos(pose[i, 2])
        s[i] = math.sin(pose[i, 2])
    r2 = 2 * g.robot_radius
    reach = g.robot_radius + g.tb
    # The grid's arrays and the working arrays (``near``: a robot's candidates), arguments read
    # once and borrowed (jit.borrow): each call of ``gather`` would otherwise count a reference
    # on each of them, an atomic operation. Without cells they are None (numba compiles that
    # case apart, and no line below reads them in it).
    near, touched, hot = borrow(near), borrow(touched), borrow(hot)
    if cells is None:
        side, cell, start, order = 0, None, None, None
    else:
        side, cell, start, order = borrow(cells)
    for p in range(_ROBOT_PASSES):
        shift_x[:] = 0.0
        shift_y[:] = 0.0
        for i in range(n):
            cx[i] = pose[i, 0] + g.body_offset * c[i]
            cy[i] = pose[i, 1] + g.body_offset * s[i]
        if cells is not None:
            build(cx, cy, g.wall_half, side, cell, start, order)
            if p == 0:
                hot[:] = True
            else:
                mark_around(side, cell, touched, hot)
            touched[:] = False
        for i in range(n):
            if cells is not None and _cold(cell, hot, i):
                continue
            m = n if cells is None else gather(i, side, cell, start, order, near, True)
            for q in range(m):
                j = q if cells is None else near[q]
                if i == j:
                    continue
                dx = cx[i] - cx[j]
                dy = cy[i] - cy[j]
                d2 = dx * dx + dy * dy
                if d2 < (r2 - _SLOP) ** 2:
                    if d2 < 1e-18:  # the same spot: part along x
                        dx, dy, d2 = (1.0 if i > j else -1.0), 0.0, 1.0
                    d = math.sqrt(d2)
                    # Each of two touching robots gives way by half the overlap.
                    k = 0.5 * (r2 - d) / d
                    shift_x[i] += k * dx
                    shift_y[i] += k * dy
                    if cells is not None:
                        touched[i] = True
        if g.blade:
            # Robot i's blade against robot j's body; both give way by half.
            for i in range(n):
                if cells is not None and _cold(cell, hot, i):
                    continue
                ax = pose[i, 0] + g.blade_x * c[i] - g.hw * s[i]
                ay = pose[i, 1] + g.blade_x * s[i] + g.hw * c[i]
                ux = 2 * g.hw * s[i]
                uy = -2 * g.hw * c[i]
                m = n if cells is None else gather(i, side, cell, start, order, near, True)
                for q in range(m):
                    j = q if cells is None else near[q]
                    if i == j:
                        continue
                    wx = cx[j] - ax
                    wy = cy[j] - ay
                    t = (wx * ux + wy * uy) / (g.blade_width * g.blade_width)
                    t = min(max(t, 0.0), 1.0)
                    dx = wx - t * ux
                    dy = wy - t * uy
                    d2 = dx * dx + dy * dy
                    if d2 < (reach - _SLOP) ** 2:
                        d = math.sqrt(max(d2, 1e-18))
                        k = 0.5 * (reach - d) / d
                        shift_x[j] += k * dx
                        shift_y[j] += k * dy
                        shift_x[i] -= k * dx
                        shift_y[i] -= k * dy
                        if cells is not None:
                            touched[i] = True
                            touched[j] = True
        any_shift = False
        for i in range(n):
            pose[i, 0] += shift_x[i]
            pose[i, 1] += shift_y[i]
            sx, sy = _wall_shift(g, pose[i, 0], pose[i, 1], c[i], s[i])
            pose[i, 0] += sx
            pose[i, 1] += sy
            if shift_x[i] != 0.0 or shift_y[i] != 0.0 or sx != 0.0 or sy != 0.0:
                any_shift = True
                if cells is not None:
                    touched[i] = True
        if not any_shift:
            return moved
        moved = True
    return moved
