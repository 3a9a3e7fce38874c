"""Geometry of the torus world: headings, the three sensor models, start configurations.

Coordinates are (x, y) with x to the right and y up, both wrapping (x mod W, y mod H); a cell's
index is ``y * W + x``. A heading is an index into :data:`HEADINGS`: 0 east (1, 0), 1 north
(0, 1), 2 west, 3 south, so a left turn (+90 degrees, (hx, hy) -> (-hy, hx)) adds 1 and a right
turn subtracts 1 (mod 4).

A sensor is a cell (f, r) relative to the agent: f cells forward (negative: behind) and r cells
to the right, i.e. position + f h + r (hy, -hx). Its value is 1 when another agent occupies it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "HEADINGS",
    "SENSOR_OFFSETS",
    "WINDOW_MAX_SIDE",
    "Poses",
    "Torus",
    "draw_starts",
    "heading_index",
    "window_table",
]

#: Unit vectors of the four headings, in left-turn order.
HEADINGS: tuple[tuple[int, int], ...] = ((1, 0), (0, 1), (-1, 0), (0, -1))

#: (forward, right) offset of each sensor, by number of sensors (the code's STD14, STD6, STD8).
SENSOR_OFFSETS: dict[int, tuple[tuple[int, int], ...]] = {
    14: (
        (1, 0), (1, 1), (1, -1), (2, 0), (2, 1), (2, -1), (0, 1), (0, -1),
        (-1, 0), (-1, 1), (-1, -1), (-2, 0), (-2, 1), (-2, -1),
    ),
    6: ((1, 0), (1, 1), (1, -1), (2, 0), (2, 1), (2, -1)),
    8: ((1, 0), (1, 1), (1, -1), (0, 1), (0, -1), (-1, 0), (-1, 1), (-1, -1)),
}  # fmt: skip


def heading_index(hx: int, hy: int) -> int:
    """The heading index of the unit vector (hx, hy); ValueError for anything else."""
    try:
        return HEADINGS.index((int(hx), int(hy)))
    except ValueError:
        raise ValueError(f"({hx}, {hy}) is not a heading; expected a unit axis vector") from None


def sensor_cell_offset(heading: int, forward: int, right: int) -> tuple[int, int]:
    """(dx, dy) of the cell ``forward`` ahead and ``right`` to the right for ``heading``."""
    hx, hy = HEADINGS[heading]
    return forward * hx + right * hy, forward * hy - right * hx


@dataclass(frozen=True)
class Torus:
    """A ``width`` x ``height`` torus and the cell indices the kernels look up."""

    width: int
    height: int

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise ValueError(f"the grid needs positive sides, got {self.width} x {self.height}")

    @property
    def cells(self) -> int:
        """Number of cells."""
        return self.width * self.height

    def cell(self, x: int, y: int) -> int:
        """The index of cell (x, y), wrapped."""
        return (y % self.height) * self.width + (x % self.width)

    def xy(self, cell: int) -> tuple[int, int]:
        """(x, y) of a cell index."""
        return cell % self.width, cell // self.width

    def neighbours(self, sensors: int) -> np.ndarray:
        """``nb[cell, heading, k]``: the cell sensor k sees from ``cell`` facing ``heading``
        (int32, shape (cells, 4, sensors)); sensor 0 is always the front cell."""
        offsets = SENSOR_OFFSETS[sensors]
        nb = np.empty((self.cells, 4, len(offsets)), dtype=np.int32)
        for y in range(self.height):
            for x in range(self.width):
                c = self.cell(x, y)
                for d in range(4):
                    for k, (f, r) in enumerate(offsets):
                        dx, dy = sensor_cell_offset(d, f, r)
                        nb[c, d, k] = self.cell(x + dx, y + dy)
        return nb


#: Largest side for which the kernels read sensors from bit rows (a row doubled fits 64 bits).
WINDOW_MAX_SIDE = 32


def window_table(sensors: int) -> np.ndarray:
    """``table[heading, part, bits]``: the sensor bits (bit k = sensor k) that 5 bits of
    occupancy around an agent stand for, to be ORed over the three parts. For headings east and
    west the parts are rows y-1, y, y+1 (bits for x-2 ... x+2, lowest first); for north and
    south columns x-1, x, x+1 (bits for y-2 ... y+2). uint16, shape (4, 3, 32)."""
    bits = np.arange(32, dtype=np.int64)
    table = np.zeros((4, 3, 32), dtype=np.int64)
    for d in range(4):
        for k, (f, r) in enumerate(SENSOR_OFFSETS[sensors]):
            dx, dy = sensor_cell_offset(d, f, r)
            part, bit = (dy + 1, dx + 2) if d % 2 == 0 else (dx + 1, dy + 2)
            table[d, part] |= ((bits >> bit) & 1) << k
    return table.astype(np.uint16)


@dataclass(frozen=True)
class Poses:
    """Agents' poses: ``x``, ``y`` and ``heading`` (int arrays of one length, index order)."""

    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray

    @classmethod
    def from_cells(cls, torus: Torus, state: np.ndarray) -> Poses:
        """Poses from the kernels' ``(N, 2)`` array of (cell, heading)."""
        state = np.asarray(state)
        return cls(state[:, 0] % torus.width, state[:, 0] // torus.width, state[:, 1].copy())

    def to_cells(self, torus: Torus) -> np.ndarray:
        """The kernels' ``(N, 2)`` int32 array of (cell, heading)."""
        cells = (np.asarray(self.y) % torus.height) * torus.width + np.asarray(self.x) % torus.width
        return np.stack([cells, np.asarray(self.heading)], axis=1).astype(np.int32)

    def vectors(self) -> tuple[np.ndarray, np.ndarray]:
        """Heading vectors (hx, hy)."""
        h = np.array(HEADINGS)[np.asarray(self.heading)]
        return h[:, 0], h[:, 1]

    def to_rows(self) -> list[list[int]]:
        """Plain rows ``[x, y, hx, hy]`` (the code's trajectory format), for JSON."""
        hx, hy = self.vectors()
        return [
            [int(a), int(b), int(c), int(d)]
            for a, b, c, d in zip(self.x, self.y, hx, hy, strict=True)
        ]

    @classmethod
    def from_rows(cls, rows) -> Poses:
        """Poses from rows ``[x, y, hx, hy]``; ValueError naming the bad row."""
        xs, ys, hs = [], [], []
        for i, row in enumerate(rows):
            if len(row) != 4:
                raise ValueError(f"pose {i}: expected [x, y, hx, hy], got {row!r}")
            try:
                hs.append(heading_index(row[2], row[3]))
            except ValueError as exc:
                raise ValueError(f"pose {i}: {exc}") from None
            xs.append(int(row[0]))
            ys.append(int(row[1]))
        return cls(np.array(xs, np.int64), np.array(ys, np.int64), np.array(hs, np.int64))


def draw_starts(
    rng: np.random.Generator, torus: Torus, agents: int, repetitions: int
) -> np.ndarray:
    """``repetitions`` start configurations, ``(repetitions, agents, 2)`` int32 (cell, heading).

    The code draws each agent's cell uniformly until it finds a free one, in index order, so the
    agents take a uniformly random ordered sample of distinct cells: drawn here in one call.
    Headings are uniform over the four.
    """
    if agents > torus.cells:
        raise ValueError(f"{agents} agents do not fit on {torus.width} x {torus.height} cells")
    out = np.empty((repetitions, agents, 2), dtype=np.int32)
    for r in range(repetitions):
        out[r, :, 0] = rng.choice(torus.cells, size=agents, replace=False)
        out[r, :, 1] = rng.integers(0, 4, size=agents)
    return out
