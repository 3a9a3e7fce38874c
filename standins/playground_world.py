"""Aseba Playground's world for an arena (docs/rehearsal.md): its size, the carpet as a ground
texture, the walls, the boxes as Enki's movable blocks and the robots' start poses, as
:class:`~simulator.world.World` places them for a seed.
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass
from typing import Final

from simulator.scenarios import WorldConfig

__all__ = [
    "BEYOND_WALLS",
    "BOUNDARY_GREY",
    "CARPET_GREY",
    "LOW_WALL_HEIGHT",
    "TEXTURE_PIXELS_PER_M",
    "VISIBLE_WALL_HEIGHT",
    "WALL_THICKNESS",
    "Arena",
]

#: Grey of the carpet in the ground texture: Enki's ground sensors read it 409-442 of 1023
#: (0.40-0.43), the lab's carpet (``simulation.ground_carpet`` 0.4).
CARPET_GREY: Final = 102
#: Grey beyond the carpet: read 923-948 (0.90-0.93), like the lab's bright boundary (0.95); both
#: lie on their side of the safety layer's ground threshold (0.55).
BOUNDARY_GREY: Final = 255
#: Texture pixels per metre: 1 cm pixels, finer than a ground sensor's footprint.
TEXTURE_PIXELS_PER_M: Final = 100
#: Enki's Thymio II has its IR sensors 3.4 cm above the floor and sees only what is at least that
#: high: walls of 5 cm are seen, walls of 2 cm are not (``simulation.walls_visible_to_ir``).
VISIBLE_WALL_HEIGHT: Final = 0.05
LOW_WALL_HEIGHT: Final = 0.02
WALL_THICKNESS: Final = 0.01
#: Floor beyond the walls to the world's own boundary, which every IR sensor sees whatever the
#: walls' height: more than the sensors' 14 cm range, so a robot at a low wall does not see it.
BEYOND_WALLS: Final = 0.15
_WORLD = """<!DOCTYPE aseba-playground>
<aseba-playground>
  <color name="wall" r="0.9" g="0.9" b="0.9" />
  <color name="box" r="0.8" g="0.6" b="0.3" />
  <world w="{width}" h="{height}" color="wall" groundTexture="{texture}"/>
{walls}
{robots}
</aseba-playground>
"""
_WALL = '  <wall x="{x:.2f}" y="{y:.2f}" l1="{l1:.2f}" l2="{l2:.2f}" h="{h:.2f}" color="wall"/>'
_BOX = (
    '  <wall x="{x:.2f}" y="{y:.2f}" l1="{l:.2f}" l2="{l:.2f}" h="{l:.2f}" color="box" '
    'mass="{mass:g}"/>'
)
_ROBOT = (
    '  <robot type="thymio2" x="{x:.2f}" y="{y:.2f}" angle="{angle:.5f}" port="{port}" '
    'name="T{index}"/>'
)
_CM = 100.0  # Playground's lengths are centimetres


@dataclass(frozen=True)
class Arena:
    """The arena of a :class:`~simulator.scenarios.WorldConfig` in Playground (lengths in metres,
    origin at the carpet's centre, as in :mod:`simulator.scenarios`)."""

    #: the carpet's extent along x
    side: float
    #: from the carpet's edge out to the walls
    wall_margin: float
    #: whether the IR sensors see the walls (their height, see :data:`LOW_WALL_HEIGHT`)
    walls_visible_to_ir: bool
    #: each robot's wheel axis (x, y) and heading (radians)
    poses: tuple[tuple[float, float, float], ...]
    #: the carpet's extent along y (``None``: ``side``, a square)
    height: float | None = None
    #: the boxes' centres (x, y): Enki's movable blocks
    boxes: tuple[tuple[float, float], ...] = ()
    #: a box's side
    box_size: float = 0.025
    #: a box's mass, kg
    box_mass: float = 0.01

    @classmethod
    def of(cls, config: WorldConfig, seed: int) -> Arena:
        """The arena of ``config`` with its robots and boxes where :class:`World` places them
        for ``seed`` (the same start as ``--backend sim`` with that seed)."""
        # Imported here: the world's module loads numba, which --help of the server does without.
        from simulator.world import World

        world = World(config, seed)
        poses = tuple((float(x), float(y), float(t)) for x, y, t in world.poses)
        boxes = tuple((float(x), float(y)) for x, y in world.box_positions)
        return cls(
            config.arena_side,
            config.wall_margin,
            config.walls_visible_to_ir,
            poses,
            height=config.arena_height,
            boxes=boxes,
            box_size=config.box_size,
            box_mass=config.box_mass,
        )

    @property
    def carpet(self) -> tuple[float, float]:
        """The carpet's (width, height)."""
        return self.side, self.side if self.height is None else self.height

    @property
    def world_size(self) -> tuple[float, float]:
        """Playground's world (width, height): walls and the floor beyond them."""
        beyond = 2 * (self.wall_margin + WALL_THICKNESS + BEYOND_WALLS)
        width, height = self.carpet
        return width + beyond, height + beyond

    def world_xml(self, ports: list[int], texture: str) -> str:
        """Playground's world file: robot ``i`` serves Aseba on TCP port ``ports[i]``."""
        if len(ports) != len(self.poses):
            raise ValueError(f"{len(ports)} ports for {len(self.poses)} robots")
        (world_w, world_h), (width, height) = self.world_size, self.carpet
        cx, cy = world_w / 2 * _CM, world_h / 2 * _CM
        inner_x = (width / 2 + self.wall_margin) * _CM
        inner_y = (height / 2 + self.wall_margin) * _CM
        t = WALL_THICKNESS * _CM
        h = (VISIBLE_WALL_HEIGHT if self.walls_visible_to_ir else LOW_WALL_HEIGHT) * _CM
        walls = [
            _WALL.format(x=cx + sx * (inner_x + t / 2), y=cy, l1=t, l2=2 * (inner_y + t), h=h)
            for sx in (-1, 1)
        ] + [
            _WALL.format(x=cx, y=cy + sy * (inner_y + t / 2), l1=2 * (inner_x + t), l2=t, h=h)
            for sy in (-1, 1)
        ]
        size = self.box_size * _CM
        # Enki's masses are about grams (its Thymio II weighs 200); a box is a movable wall.
        boxes = [
            _BOX.format(x=cx + x * _CM, y=cy + y * _CM, l=size, mass=self.box_mass * 1000)
            for x, y in self.boxes
        ]
        robots = [
            _ROBOT.format(x=cx + x * _CM, y=cy + y * _CM, angle=a, port=port, index=i)
            for i, ((x, y, a), port) in enumerate(zip(self.poses, ports, strict=True))
        ]
        return _WORLD.format(
            width=f"{world_w * _CM:.2f}",
            height=f"{world_h * _CM:.2f}",
            texture=texture,
            walls="\n".join(walls + boxes),
            robots="\n".join(robots),
        )

    def ground_png(self) -> bytes:
        """The floor as a greyscale PNG: the carpet dark, the rest bright."""
        (world_w, world_h), (width, height) = self.world_size, self.carpet
        columns = math.ceil(world_w * TEXTURE_PIXELS_PER_M)
        rows = math.ceil(world_h * TEXTURE_PIXELS_PER_M)
        # Whether the i-th column (or row) of pixels lies over the carpet; the carpet is centred.
        over_x = [
            abs((i + 0.5) * world_w / columns - world_w / 2) < width / 2 for i in range(columns)
        ]
        over_y = [abs((j + 0.5) * world_h / rows - world_h / 2) < height / 2 for j in range(rows)]
        carpet_row = bytes(CARPET_GREY if inside else BOUNDARY_GREY for inside in over_x)
        bright_row = bytes([BOUNDARY_GREY]) * columns
        # Each row starts with PNG's filter byte 0 (none).
        raw = b"".join(b"\0" + (carpet_row if inside else bright_row) for inside in over_y)

        def chunk(kind: bytes, data: bytes) -> bytes:
            crc = zlib.crc32(kind + data) & 0xFFFFFFFF
            return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

        header = struct.pack(">IIBBBBB", columns, rows, 8, 0, 0, 0, 0)  # 8-bit greyscale
        return (
            b"\x89PNG\r\n\x1a\n"
            + chunk(b"IHDR", header)
            + chunk(b"IDAT", zlib.compress(raw))
            + chunk(b"IEND", b"")
        )
