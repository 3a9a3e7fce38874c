"""Neighbour lookup for large swarms: a uniform grid of cells (a cell list) over the arena.

Robot-robot contacts (:mod:`.contacts`) and the IR sensing of other robots (:mod:`.sensing`)
only concern robots closer than a range: the bodies' diameter (the blade's reach with a blade)
and the IR's range beyond a sensor. From :data:`GRID_ROBOTS` robots on (``Geometry.grid_robots``,
``Sensing.grid_robots``) the kernels put every robot's body centre into square cells at least as
wide as that range, rebuilt wherever positions change, and look for a robot's neighbours only
in the 3 x 3 cells around its own: a step costs O(N) instead of O(N^2). Below, every pair is
looked at (one cell holds every robot).

Both give the same results bit for bit: a robot's candidates are visited in increasing index,
as the all-pairs loops visit them (``gather(..., ordered=True)`` sorts them), so every push is
added in the same order; the IR takes the minimum of its distances, which no order changes.
Robots a rounding error beyond the walls count in the outermost cells, which keeps every pair
within range in neighbouring cells.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from minimize_surprise.jit import kernel

__all__ = [
    "GRID_ROBOTS",
    "Cells",
    "build",
    "gather",
    "grid_choice",
    "grid_side",
    "mark_around",
    "new_cells",
]

#: From this many robots on, contacts and sensing find neighbours in the grid; below it looking at
#: every pair is as fast or faster (measured at the basic scenario's density with
#: ``benchmarks/scale.py``: docs/simulation.md, "Figures behind the code's choices"). The paper's
#: swarms (4 and 10 robots) keep the all-pairs loops.
GRID_ROBOTS = 40


def grid_choice(robots: int, grid_robots: int) -> bool | None:
    """The ``grid`` argument of the kernels that look for neighbours (``sense``, ``step_world``)
    for an arena of ``robots``: None below ``grid_robots``, where they look at every pair and
    need compile nothing else, True from it on, where they decide at each call."""
    return None if robots < grid_robots else True


# Cells are this much (metres) wider than the range they serve, so that rounding in the cell
# index never puts two robots within range two cells apart.
_MARGIN = 1e-6


@kernel
def grid_side(wall_half: float, reach: float, n: int) -> int:
    """Cells per side of a grid for ``n`` robots between walls ``wall_half`` from the centre,
    for pairs closer than ``reach``: as many as fit at least ``reach`` wide, at most about
    2 sqrt(n) (few robots in a large arena need no more cells than robots)."""
    k = int(2.0 * wall_half / (reach + _MARGIN))
    return max(1, min(k, 2 * int(math.sqrt(n)) + 1))


class Cells(NamedTuple):
    """A grid of ``side`` x ``side`` cells over N points: ``cell`` (N) each point's cell; the
    points of cell c are ``order[start[c]:start[c + 1]]``, in increasing index (:func:`build`).
    """

    side: int
    cell: np.ndarray
    start: np.ndarray
    order: np.ndarray


@kernel
def new_cells(n: int, side: int) -> Cells:
    """An empty grid of ``side`` x ``side`` cells for ``n`` points."""
    return Cells(
        side,
        np.empty(n, dtype=np.int64),
        np.empty(side * side + 1, dtype=np.int64),
        np.empty(n, dtype=np.int64),
    )


@kernel
def build(
    xs: np.ndarray, ys: np.ndarray, half: float, side: int, cell: np.ndarray,
    start: np.ndarray, order: np.ndarray,
) -> None:  # fmt: skip
    """Sort the points (``xs``, ``ys``) into ``side`` x ``side`` cells covering [-half, half]^2
    (the arrays of :class:`Cells`); a point beyond (or NaN) counts in the outermost cell."""
    n = xs.shape[0]
    size = 2.0 * half / side
    start[:] = 0
    for i in range(n):
        fx = (xs[i] + half) / size
        fy = (ys[i] + half) / size
        gx = 0 if not fx >= 0.0 else (side - 1 if fx >= side else int(fx))
        gy = 0 if not fy >= 0.0 else (side - 1 if fy >= side else int(fy))
        c = gy * side + gx
        cell[i] = c
        start[c + 1] += 1
    for c in range(side * side):
        start[c + 1] += start[c]
    for i in range(n):
        c = cell[i]
        # start[c] counts up while the cell fills, then is put back below.
        order[start[c]] = i
        start[c] += 1
    for c in range(side * side - 1, 0, -1):
        start[c] = start[c - 1]
    start[0] = 0


@kernel(inline=True)
def _around(side: int, c: int) -> tuple[int, int, int, int]:
    # The 3 x 3 cells around cell c, within the grid: columns x0..x1-1, rows y0..y1-1.
    cx, cy = c % side, c // side
    return max(cx - 1, 0), min(cx + 2, side), max(cy - 1, 0), min(cy + 2, side)


@kernel(inline=True)
def mark_around(side: int, cell: np.ndarray, chosen: np.ndarray, out: np.ndarray) -> None:
    """``out`` (side * side) True at every cell of the 3 x 3 around a ``chosen`` point's cell
    (``cell`` each point's), False elsewhere: the cells whose points may meet a chosen one."""
    out[:] = False
    for i in range(chosen.shape[0]):
        if chosen[i]:
            x0, x1, y0, y1 = _around(side, cell[i])
            for gy in range(y0, y1):
                for gx in range(x0, x1):
                    out[gy * side + gx] = True


@kernel(inline=True)
def gather(
    i: int, side: int, cell: np.ndarray, start: np.ndarray, order: np.ndarray, out: np.ndarray,
    ordered: bool,
) -> int:  # fmt: skip
    """Point ``i``'s candidate neighbours (itself included) into ``out``: every point in the
    3 x 3 cells around its own; returns their number. With ``ordered``, in increasing
    index."""
    x0, x1, y0, y1 = _around(side, cell[i])
    m = 0
    for gy in range(y0, y1):
        for gx in range(x0, x1):
            d = gy * side + gx
            for p in range(start[d], start[d + 1]):
                out[m] = order[p]
                m += 1
    if ordered:
        # Insertion sort: a handful of candidates, in up to nine increasing runs.
        for a in range(1, m):
            v = out[a]
            b = a - 1
            while b >= 0 and out[b] > v:
                out[b + 1] = out[b]
                b -= 1
            out[b + 1] = v
    return m
