"""The nine patterns of paper Sec. IV-A and solution quality, as the authors' classifier scripts
compute them on the agents' final poses, but for lines across the torus border, whose ends are
trimmed once, as the paper says (docs/gridworld.md, "Lines across the border").

Each measure gives the fraction of agents that belong to its pattern; every neighbourhood wraps
around the torus. Codes: LN lines, PR pairs, SQ squares, TL triangular lattice, RD random
dispersion, AG aggregation, CL clustering, LG loose grouping, SW swirls. :func:`classify` takes
the pattern with the largest fraction (ties to the first in :data:`PATTERNS`: CL, AG, LG, LN, PR,
TL, SQ, SW, RD) and its fraction as solution quality. The grouping measure gives one fraction and
one label (AG, CL or LG); the score vector holds it under that label and 0 under the other two.
The rules, one per function below, are spelled out in docs/gridworld.md.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from gridworld.world import Poses

__all__ = [
    "PATTERNS",
    "PATTERN_NAMES",
    "Classification",
    "Grid",
    "classify",
    "grouping",
    "lines",
    "pairs",
    "poses_of",
    "random_dispersion",
    "scores",
    "squares",
    "swirls",
    "triangular_lattice",
]

#: Pattern codes in tie-break order.
PATTERNS: tuple[str, ...] = ("CL", "AG", "LG", "LN", "PR", "TL", "SQ", "SW", "RD")

#: Long names of the codes.
PATTERN_NAMES: dict[str, str] = {
    "CL": "clustering",
    "AG": "aggregation",
    "LG": "loose grouping",
    "LN": "lines",
    "PR": "pairs",
    "TL": "triangular lattice",
    "SQ": "squares",
    "SW": "swirls",
    "RD": "random dispersion",
}

_VN = ((1, 0), (-1, 0), (0, 1), (0, -1))
_DIAGONAL = ((1, 1), (1, -1), (-1, 1), (-1, -1))


class Grid:
    """Final poses on a ``width`` x ``height`` torus, indexed for the measures.

    ``pos[i]`` is agent i's (x, y), ``head[i]`` its heading vector; ``at`` maps a cell to the
    agent on it. Raises ValueError if two agents share a cell.
    """

    def __init__(self, width: int, height: int, poses: Poses) -> None:
        self.width, self.height = width, height
        hx, hy = poses.vectors()
        self.pos = [
            (int(x) % width, int(y) % height) for x, y in zip(poses.x, poses.y, strict=True)
        ]
        self.head = [(int(a), int(b)) for a, b in zip(hx, hy, strict=True)]
        self.n = len(self.pos)
        self.at: dict[tuple[int, int], int] = {}
        for i, cell in enumerate(self.pos):
            if cell in self.at:
                raise ValueError(f"agents {self.at[cell]} and {i} share cell {cell}")
            self.at[cell] = i

    def wrap(self, x: int, y: int) -> tuple[int, int]:
        """The cell (x, y) wrapped onto the torus."""
        return x % self.width, y % self.height

    def occupied(self, x: int, y: int) -> bool:
        """Whether an agent is on cell (x, y) (wrapped)."""
        return self.wrap(x, y) in self.at

    def agent(self, x: int, y: int) -> int | None:
        """The agent on cell (x, y) (wrapped), or None."""
        return self.at.get(self.wrap(x, y))

    def count(self, i: int, offsets) -> int:
        """How many of the cells at ``offsets`` from agent i are occupied."""
        x, y = self.pos[i]
        return sum(self.occupied(x + dx, y + dy) for dx, dy in offsets)


# --- lines ------------------------------------------------------------------------------------


def _adjacent_on_ring(coords: list[int], side: int) -> bool:
    coords = sorted(coords)
    if 0 in coords and side - 1 in coords:
        return True
    return any(b == a + 1 for a, b in itertools.pairwise(coords))


def _flanks_ok(grid: Grid, members: list[int], axis: int, side: int) -> bool:
    # For each flanking row (column): at most ceil(len / 2) occupied cells, no two adjacent.
    limit = math.ceil(len(members) / 2)
    for sign in (1, -1):
        coords = []
        for i in members:
            x, y = grid.pos[i]
            if axis == 0 and grid.occupied(x, y + sign):
                coords.append(x)
            elif axis == 1 and grid.occupied(x + sign, y):
                coords.append(y)
        if len(coords) > limit or _adjacent_on_ring(coords, side):
            return False
    return True


def line_members(grid: Grid) -> set[int]:
    """Agents in lines (LN).

    Repeatedly, the remaining agent with the lowest (x, y) seeds a run: the maximal sequence of
    remaining agents on consecutive cells of its row (heading along x) or column (along y) whose
    headings all lie along that axis; the run's agents are then no longer remaining. A run as
    long as the side is judged as it is; a shorter run of at least 3 loses end agents whose front
    cell is not in the run (ends must face inwards), then needs at least 3 agents with ends
    facing opposite ways. Either way each flanking row (column) may hold at most ceil(len / 2)
    agents beside the run, no two of them adjacent; else the whole run is rejected.
    """
    remaining = set(range(grid.n))
    members: set[int] = set()
    while len(remaining) > 1:
        seed = min(remaining, key=lambda i: grid.pos[i])
        axis = 0 if grid.head[seed][0] != 0 else 1
        side = grid.width if axis == 0 else grid.height
        step = (1, 0) if axis == 0 else (0, 1)

        run = [seed]
        remaining.discard(seed)
        for direction in (1, -1):
            x, y = grid.pos[seed]
            while len(run) < side:
                x, y = grid.wrap(x + direction * step[0], y + direction * step[1])
                j = grid.agent(x, y)
                if j is None or j not in remaining or grid.head[j][axis] == 0:
                    break
                run.append(j)
                remaining.discard(j)
        if len(run) == side:
            candidate = run
        elif len(run) > 2:
            candidate = _trim(grid, run, axis, side)
            if len(candidate) < 3:
                continue
        else:
            continue
        if _flanks_ok(grid, candidate, axis, side):
            members.update(candidate)
    return members


def _trim(grid: Grid, run: list[int], axis: int, side: int) -> list[int]:
    # Order the run from one end to the other along the axis (it is a contiguous arc shorter
    # than the side), then drop end agents that do not face into the run, first at the start.
    coord = {grid.pos[i][axis]: i for i in run}
    start = next(c for c in coord if (c - 1) % side not in coord)
    ordered = [coord[(start + k) % side] for k in range(len(run))]

    def faces_in(i: int, members: list[int]) -> bool:
        x, y = grid.pos[i]
        hx, hy = grid.head[i]
        front = grid.wrap(x + hx, y + hy)
        return any(grid.pos[j] == front for j in members)

    while ordered and not faces_in(ordered[0], ordered):
        ordered.pop(0)
    while ordered and not faces_in(ordered[-1], ordered):
        ordered.pop()
    if not ordered or grid.head[ordered[0]][axis] != -grid.head[ordered[-1]][axis]:
        return []
    return ordered


def lines(grid: Grid) -> float:
    """Fraction of agents in lines (see :func:`line_members`)."""
    return len(line_members(grid)) / grid.n


# --- pairs ------------------------------------------------------------------------------------


def pair_members(grid: Grid, in_line: set[int] | None = None) -> set[int]:
    """Agents in pairs (PR): in index order, an agent A whose front cell holds a not yet used
    agent B with the opposite heading (head to head). Both are used from then on; they are a
    pair unless one of them is in a line or the two cells beside them on the same side are both
    occupied."""
    if in_line is None:
        in_line = line_members(grid)
    used: set[int] = set()
    members: set[int] = set()
    for a in range(grid.n):
        if a in used:
            continue
        used.add(a)
        (x, y), (hx, hy) = grid.pos[a], grid.head[a]
        b = grid.agent(x + hx, y + hy)
        if b is None or b in used or grid.head[b] != (-hx, -hy):
            continue
        used.add(b)
        bx, by = grid.pos[b]
        flanked = any(
            grid.occupied(x + sx, y + sy) and grid.occupied(bx + sx, by + sy)
            for sx, sy in ((hy, -hx), (-hy, hx))
        )
        if a not in in_line and b not in in_line and not flanked:
            members.update((a, b))
    return members


def pairs(grid: Grid) -> float:
    """Fraction of agents in pairs (see :func:`pair_members`)."""
    return len(pair_members(grid)) / grid.n


# --- squares and triangular lattice -------------------------------------------------------------

_SQUARE_PARTNERS = ((2, 0), (0, 2), (2, 2))
_SQUARE_EMPTY = tuple(
    (dx, dy)
    for dx in range(-1, 4)
    for dy in range(-1, 4)
    if (dx, dy) not in ((0, 0), *_SQUARE_PARTNERS)
)
_LATTICE_PARTNERS = ((2, 0), (-2, 0), (0, 2), (0, -2), (1, 1), (1, -1), (-1, 1), (-1, -1))
_LATTICE_EMPTY = (
    (1, 0), (-1, 0), (0, 1), (0, -1),
    (1, 2), (-1, 2), (1, -2), (-1, -2), (2, 1), (2, -1), (-2, 1), (-2, -1),
)  # fmt: skip


def _motif_members(grid: Grid, partners, empty) -> set[int]:
    members: set[int] = set()
    for i in range(grid.n):
        x, y = grid.pos[i]
        found = [grid.agent(x + dx, y + dy) for dx, dy in partners]
        if all(j is not None for j in found) and grid.count(i, empty) == 0:
            members.add(i)
            members.update(j for j in found if j is not None)
    return members


def square_members(grid: Grid) -> set[int]:
    """Agents in squares (SQ): an agent at (x, y) with agents at (x+2, y), (x, y+2) and
    (x+2, y+2) and the other 21 cells of the box (x-1 ... x+3) x (y-1 ... y+3) empty makes all
    four members. Headings do not matter."""
    return _motif_members(grid, _SQUARE_PARTNERS, _SQUARE_EMPTY)


def squares(grid: Grid) -> float:
    """Fraction of agents in squares (see :func:`square_members`)."""
    return len(square_members(grid)) / grid.n


def lattice_members(grid: Grid) -> set[int]:
    """Agents in a triangular lattice (TL): an agent with all of (+-2, 0), (0, +-2), (+-1, +-1)
    occupied and all of (+-1, 0), (0, +-1), (+-1, +-2), (+-2, +-1) empty makes itself and those
    eight members (a checkerboard). Headings do not matter."""
    return _motif_members(grid, _LATTICE_PARTNERS, _LATTICE_EMPTY)


def triangular_lattice(grid: Grid) -> float:
    """Fraction of agents in a triangular lattice (see :func:`lattice_members`)."""
    return len(lattice_members(grid)) / grid.n


# --- random dispersion ------------------------------------------------------------------------


def random_dispersion(grid: Grid, in_line: set[int] | None = None) -> float:
    """Fraction of agents randomly dispersed (RD): no von Neumann neighbour or at most one Moore
    neighbour, and not a member of a line, pair, square or triangular lattice."""
    if in_line is None:
        in_line = line_members(grid)
    structured = (
        in_line | pair_members(grid, in_line) | square_members(grid) | lattice_members(grid)
    )
    count = 0
    for i in range(grid.n):
        vn = grid.count(i, _VN)
        moore = vn + grid.count(i, _DIAGONAL)
        if (vn == 0 or moore <= 1) and i not in structured:
            count += 1
    return count / grid.n


# --- grouping ---------------------------------------------------------------------------------


def clusters(grid: Grid) -> list[set[int]]:
    """The clusters of the grouping measure. A core agent has at least 3 von Neumann and at least
    6 Moore neighbours. Agents in index order that are not yet in a cluster seed one when they
    are cores: the cluster holds the cores Moore-connected to the seed through cores and every
    Moore neighbour of those cores (non-core members are not expanded)."""
    moore = _VN + _DIAGONAL

    def neighbours(i: int) -> list[int]:
        x, y = grid.pos[i]
        return [j for dx, dy in moore if (j := grid.agent(x + dx, y + dy)) is not None]

    def core(i: int) -> bool:
        return grid.count(i, _VN) >= 3 and grid.count(i, moore) >= 6

    assigned: set[int] = set()
    found: list[set[int]] = []
    for seed in range(grid.n):
        if seed in assigned:
            continue
        assigned.add(seed)
        if not core(seed):
            continue
        cluster = {seed}
        checked = {seed}
        frontier = []
        for j in neighbours(seed):
            cluster.add(j)
            assigned.add(j)
            if j not in frontier:
                frontier.append(j)
        while frontier:
            i = frontier.pop(0)
            checked.add(i)
            if core(i):
                for j in neighbours(i):
                    cluster.add(j)
                    assigned.add(j)
                    if j not in checked and j not in frontier:
                        frontier.append(j)
        found.append(cluster)
    return found


def grouping(grid: Grid) -> tuple[str, float]:
    """The grouping label and fraction: clusters (:func:`clusters`) are linked when a member of
    one has a von Neumann neighbour in the other, links being transitive. One cluster is
    aggregation (AG); two or more all linked are loose grouping (LG); otherwise (no cluster, or
    unlinked ones) clustering (CL). The fraction is the union of all clusters' members over N."""
    found = clusters(grid)
    members = set().union(*found) if found else set()
    fraction = len(members) / grid.n
    if len(found) == 1:
        return "AG", fraction
    if len(found) < 2:
        return "CL", fraction
    # link graph between clusters, then: is it connected?
    parent = list(range(len(found)))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, cluster in enumerate(found):
        for i in cluster:
            x, y = grid.pos[i]
            for dx, dy in _VN:
                j = grid.agent(x + dx, y + dy)
                if j is None:
                    continue
                for b, other in enumerate(found):
                    if b != a and j in other:
                        parent[root(a)] = root(b)
    linked = len({root(a) for a in range(len(found))}) == 1
    return ("LG" if linked else "CL"), fraction


# --- swirls -----------------------------------------------------------------------------------


def swirl_members(grid: Grid) -> set[int]:
    """Agents in swirls (SW): in index order, an agent A not yet used whose front cell holds an
    unused B turned 90 degrees from it, with an unused C in B's front cell facing against A and
    an unused D in C's front cell facing against B (so D faces A): a 2 x 2 block circling one
    way. The four are used from then on; they are a swirl when at most one of the 12 cells
    around the block is occupied."""
    used: set[int] = set()
    members: set[int] = set()
    for a in range(grid.n):
        if a in used:
            continue
        used.add(a)
        (x, y), (hx, hy) = grid.pos[a], grid.head[a]
        b = grid.agent(x + hx, y + hy)
        if b is None or b in used or grid.head[b] not in ((-hy, hx), (hy, -hx)):
            continue
        bhx, bhy = grid.head[b]
        bx, by = grid.pos[b]
        c = grid.agent(bx + bhx, by + bhy)
        d = grid.agent(x + bhx, y + bhy)
        if (
            c is None
            or d is None
            or c in used
            or d in used
            or grid.head[c] != (-hx, -hy)
            or grid.head[d] != (-bhx, -bhy)
        ):
            continue
        block = (a, b, c, d)
        used.update(block)
        cells = {grid.pos[i] for i in block}
        corner = next(
            (cx, cy)
            for cx, cy in cells
            if grid.wrap(cx + 1, cy) in cells and grid.wrap(cx, cy + 1) in cells
        )
        ring = [(dx, -1) for dx in range(-1, 3)] + [(dx, 2) for dx in range(-1, 3)]
        ring += [(-1, 0), (-1, 1), (2, 0), (2, 1)]
        around = sum(grid.occupied(corner[0] + dx, corner[1] + dy) for dx, dy in ring)
        if around <= 1:
            members.update(block)
    return members


def swirls(grid: Grid) -> float:
    """Fraction of agents in swirls (see :func:`swirl_members`)."""
    return len(swirl_members(grid)) / grid.n


# --- classification ---------------------------------------------------------------------------


def scores(grid: Grid) -> dict[str, float]:
    """Every pattern's fraction, in :data:`PATTERNS` order."""
    in_line = line_members(grid)
    label, fraction = grouping(grid)
    out = dict.fromkeys(PATTERNS, 0.0)
    out[label] = fraction
    out["LN"] = len(in_line) / grid.n
    out["PR"] = len(pair_members(grid, in_line)) / grid.n
    out["TL"] = triangular_lattice(grid)
    out["SQ"] = squares(grid)
    out["SW"] = swirls(grid)
    out["RD"] = random_dispersion(grid, in_line)
    return out


@dataclass(frozen=True)
class Classification:
    """The dominant pattern, its fraction (solution quality, 0-1) and the full score vector."""

    pattern: str
    quality: float
    scores: dict[str, float]


def classify(width: int, height: int, poses: Poses) -> Classification:
    """Classify final poses on a ``width`` x ``height`` torus (ties: first in :data:`PATTERNS`)."""
    vector = scores(Grid(width, height, poses))
    best = max(PATTERNS, key=lambda p: (vector[p], -PATTERNS.index(p)))
    return Classification(best, vector[best], vector)


def poses_of(cells: list[tuple[int, int, int, int]]) -> Poses:
    """Poses from ``(x, y, hx, hy)`` tuples (for hand-made grids)."""
    return Poses.from_rows([list(c) for c in cells])
