"""Arenas as files: the floor, its rim, the walls, the boxes, where the robots start and the light
(docs/arenas.md).

An arena file is YAML, one :class:`Arena`; what it leaves out comes from the setting and the
simulator's defaults, so a file says only what its arena is. The shipped arenas live beside this
module (``simulator/arenas/*.yaml``) and are named by their file's stem (:func:`shipped_arenas`);
an experiment's ``arena`` key is such a name or a file's path.

Coordinates are the simulator's: the origin at the centre of the floor, x to the right along its
``width``, y up along its ``height``, metres; headings in degrees counter-clockwise from x.
An arena turns into the simulated world's parameters (:meth:`Arena.world`); the experiment's
``simulation`` mapping still overrides any of them.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
from msgspec import UNSET, UnsetType

from minimize_surprise.config import Strict, decode, read_yaml
from minimize_surprise.errors import ConfigError

__all__ = [
    "ARENA_DIRECTORY",
    "Arena",
    "BoxField",
    "Floor",
    "Light",
    "Start",
    "Walls",
    "arena_path",
    "is_arena_path",
    "load_arena",
    "shipped_arenas",
]

#: Where the shipped arena files are.
ARENA_DIRECTORY = Path(__file__).with_name("arenas")

Positive = Annotated[float, msgspec.Meta(gt=0.0)]
NonNegative = Annotated[float, msgspec.Meta(ge=0.0)]
Unit = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
#: (x0, y0, x1, y1)
Region = tuple[float, float, float, float]
#: (x, y, heading in degrees)
Pose = tuple[float, float, float]
#: The most of a region boxes may cover: beyond it random placement cannot find room (the
#: simulator's ``box_coverage`` has the same limit).
MAX_BOX_COVERAGE = 0.4
#: A Thymio II's body as the simulator approximates it (``WorldConfig``'s ``robot_radius`` and
#: ``body_offset``; a test keeps them equal): a circle of this radius centred this far ahead of
#: the wheel axis. A fixed start's poses are checked against it when the file is read.
BODY_RADIUS = 0.058
BODY_OFFSET = 0.025


class Floor(Strict, frozen=True):
    """What the ground sensors see: the floor and, beyond its edge, the rim (a bright border,
    mirror film, the carpet's end)."""

    #: extent along x, metres
    width: Positive
    #: extent along y, metres (default: ``width``, a square)
    height: Positive | UnsetType = UNSET
    #: the ground sensors' normalised value on the floor (the real carpet: about 0.4)
    reflectance: Unit | UnsetType = UNSET
    #: the ground sensors' normalised value beyond the floor's edge
    rim_reflectance: Unit | UnsetType = UNSET


class Walls(Strict, frozen=True):
    """The walls: a rectangle around the floor, ``margin`` behind its edge on every side."""

    #: distance from the floor's edge out to the walls, metres
    margin: NonNegative | UnsetType = UNSET
    #: whether the robots' horizontal IR sensors see the walls (low walls: no)
    visible_to_ir: bool | UnsetType = UNSET


class BoxField(Strict, frozen=True):
    """Boxes to push, scattered on the floor (or in ``region``)."""

    #: how many boxes (instead of ``coverage``)
    count: Annotated[int, msgspec.Meta(ge=0)] | UnsetType = UNSET
    #: the share of the floor (or of ``region``) the boxes cover (the paper: 0.14)
    coverage: Annotated[float, msgspec.Meta(ge=0.0, le=MAX_BOX_COVERAGE)] | UnsetType = UNSET
    #: a (cubic) box's side, metres
    size: Positive | UnsetType = UNSET
    #: a box's mass, kg (the Playground's boxes)
    mass: Positive | UnsetType = UNSET
    #: "random" (uniform) or "grid" (the authors' Webots layout)
    layout: Literal["random", "grid"] | UnsetType = UNSET
    #: (x0, y0, x1, y1): where the boxes lie ("random" layout; default the whole floor)
    region: Region | UnsetType = UNSET
    #: the side of a square around the centre kept free of boxes
    clear_centre: NonNegative | UnsetType = UNSET


class Start(Strict, frozen=True):
    """Where the robots start: at random, on a ring around the centre facing out, or at fixed
    poses (one per robot)."""

    #: "random", "ring" (around the centre, facing out) or "fixed"
    kind: Literal["random", "ring", "fixed"]
    #: "random": (x0, y0, x1, y1) the robots' bodies start in (default the whole floor)
    region: Region | UnsetType = UNSET
    #: "fixed": one [x, y, heading in degrees] per robot, the point between its wheels
    poses: list[Pose] | UnsetType = UNSET
    #: "ring": the wheel axes' distance from the centre (default: neighbours just apart)
    ring: NonNegative | UnsetType | None = UNSET
    #: "ring": the first robot's direction from the centre, degrees
    ring_phase: float | UnsetType = UNSET


class Light(Strict, frozen=True):
    """A lamp above the floor (the gradient arena); without one the light is uniform."""

    #: the point under the lamp
    position: tuple[float, float] | UnsetType = UNSET
    #: the light value under the lamp
    centre: Unit | UnsetType = UNSET
    #: the light value at the floor's corners
    corner: Unit | UnsetType = UNSET
    #: how the light falls off (1: inverse square)
    exponent: Annotated[float, msgspec.Meta(gt=0.0, le=3.0)] | UnsetType = UNSET


class Arena(Strict, frozen=True):
    """One arena (see the module docstring)."""

    #: the arena's name, as reports and pictures show it
    name: str
    #: the floor
    floor: Floor
    #: what the arena is, in a sentence or two (which experiment of the paper it stands for)
    description: str = ""
    #: the walls
    walls: Walls = Walls()
    #: boxes to push (none if left out)
    boxes: BoxField | None = None
    #: where the robots start (the simulator's default: at random on the floor)
    start: Start | None = None
    #: a lamp (uniform light if left out)
    light: Light | None = None

    def __post_init__(self) -> None:
        width = self.floor.width
        height = width if isinstance(self.floor.height, UnsetType) else self.floor.height
        half_w, half_h = width / 2, height / 2
        boxes, start = self.boxes, self.start
        if boxes is not None:
            if not isinstance(boxes.count, UnsetType) and not isinstance(boxes.coverage, UnsetType):
                raise ValueError("`boxes.count`: give either count or coverage, not both")
            region = _given(boxes.region)
            if region is not None:
                _check_region("boxes.region", region, half_w, half_h)
            size = 0.025 if isinstance(boxes.size, UnsetType) else boxes.size
            if size >= min(width, height):
                raise ValueError(f"`boxes.size`: {size} m is not smaller than the floor")
            if not isinstance(boxes.count, UnsetType):
                x0, y0, x1, y1 = region or (-half_w, -half_h, half_w, half_h)
                fit = int(MAX_BOX_COVERAGE * (x1 - x0) * (y1 - y0) / size**2)
                if boxes.count > fit:
                    raise ValueError(
                        f"`boxes.count`: {boxes.count} boxes of {size} m do not fit; at most "
                        f"{fit} fit ({MAX_BOX_COVERAGE:.0%} of their "
                        f"{(x1 - x0) * (y1 - y0):.3g} m^2)"
                    )
        if start is not None:
            self._check_start(start, half_w, half_h)

    @staticmethod
    def _check_start(start: Start, half_w: float, half_h: float) -> None:
        region = _given(start.region)
        poses = _given(start.poses)
        if start.kind != "random" and region is not None:
            raise ValueError("`start.region`: only a random start has a region")
        if start.kind != "fixed" and poses is not None:
            raise ValueError("`start.poses`: only a fixed start has poses")
        if start.kind != "ring" and not (
            isinstance(start.ring, UnsetType) and isinstance(start.ring_phase, UnsetType)
        ):
            raise ValueError("`start.ring`: only a ring start has a ring")
        if region is not None:
            _check_region("start.region", region, half_w, half_h)
        if start.kind == "fixed":
            if not poses:
                raise ValueError("`start.poses`: a fixed start needs a pose per robot")
            centres: list[tuple[float, float]] = []
            for i, (x, y, heading) in enumerate(poses):
                if abs(x) >= half_w or abs(y) >= half_h:
                    raise ValueError(
                        f"`start.poses`: pose {i + 1} ({x:g}, {y:g}) is outside the "
                        f"{2 * half_w:g} x {2 * half_h:g} m floor"
                    )
                cx = x + BODY_OFFSET * math.cos(math.radians(heading))
                cy = y + BODY_OFFSET * math.sin(math.radians(heading))
                if abs(cx) + BODY_RADIUS > half_w or abs(cy) + BODY_RADIUS > half_h:
                    raise ValueError(
                        f"`start.poses`: the robot at pose {i + 1} ({x:g}, {y:g}) reaches "
                        f"beyond the {2 * half_w:g} x {2 * half_h:g} m floor"
                    )
                for j, (ox, oy) in enumerate(centres):
                    if math.hypot(cx - ox, cy - oy) < 2 * BODY_RADIUS:
                        raise ValueError(
                            f"`start.poses`: poses {j + 1} and {i + 1} overlap: their bodies "
                            "would touch at the start"
                        )
                centres.append((cx, cy))

    def world(self) -> dict[str, Any]:
        """The simulated world's parameters this arena gives (``simulator.scenarios.WorldConfig``
        keys), only those it states."""
        floor, walls = self.floor, self.walls
        out: dict[str, Any] = {"arena_side": floor.width}
        if not isinstance(floor.height, UnsetType) and floor.height != floor.width:
            out["arena_height"] = floor.height
        _put(out, "ground_carpet", floor.reflectance)
        _put(out, "ground_outside", floor.rim_reflectance)
        _put(out, "wall_margin", walls.margin)
        _put(out, "walls_visible_to_ir", walls.visible_to_ir)
        if self.boxes is not None:
            b = self.boxes
            out["boxes"] = True
            _put(out, "box_number", b.count)
            _put(out, "box_coverage", b.coverage)
            _put(out, "box_size", b.size)
            _put(out, "box_mass", b.mass)
            _put(out, "box_layout", b.layout)
            _put(out, "box_region", _listed(b.region))
            _put(out, "box_clear_centre", b.clear_centre)
        if self.start is not None:
            s = self.start
            out["start"] = {"random": "random", "ring": "centre", "fixed": "fixed"}[s.kind]
            _put(out, "start_region", _listed(s.region))
            if not isinstance(s.poses, UnsetType):
                out["start_poses"] = [list(p) for p in s.poses]
                out["robots"] = len(s.poses)
            _put(out, "start_ring", s.ring)
            _put(out, "start_ring_phase", s.ring_phase)
        if self.light is not None:
            light = self.light
            out["light"] = True
            _put(out, "light_position", _listed(light.position))
            _put(out, "light_centre", light.centre)
            _put(out, "light_corner", light.corner)
            _put(out, "light_exponent", light.exponent)
        return out

    @property
    def size(self) -> tuple[float, float]:
        """The floor's (width, height), metres."""
        height = self.floor.width if isinstance(self.floor.height, UnsetType) else self.floor.height
        return self.floor.width, height


def _given(value: Any) -> Any:
    return None if isinstance(value, UnsetType) else value


def _listed(value: Any) -> Any:
    return value if isinstance(value, UnsetType) else list(value)


def _put(out: dict[str, Any], key: str, value: Any) -> None:
    if not isinstance(value, UnsetType):
        out[key] = value


def _check_region(key: str, region: Region, half_w: float, half_h: float) -> None:
    x0, y0, x1, y1 = region
    if not all(math.isfinite(v) for v in region):
        raise ValueError(f"`{key}`: expected finite numbers, got {list(region)}")
    if not (x0 < x1 and y0 < y1):
        raise ValueError(f"`{key}`: expected [x0, y0, x1, y1] with x0 < x1 and y0 < y1")
    if x0 < -half_w or x1 > half_w or y0 < -half_h or y1 > half_h:
        raise ValueError(
            f"`{key}`: {list(region)} reaches beyond the {2 * half_w:g} x {2 * half_h:g} m floor"
        )


def shipped_arenas() -> tuple[str, ...]:
    """The names of the arenas that ship with the simulator, sorted."""
    return tuple(sorted(p.stem for p in ARENA_DIRECTORY.glob("*.yaml")))


def is_arena_path(value: str) -> bool:
    """Whether an experiment's ``arena`` value is a file's path rather than a shipped name."""
    return "/" in value or value.endswith((".yaml", ".yml"))


def arena_path(value: str, *, file: str | Path | None = None, key: str = "arena") -> Path:
    """The file of arena ``value``: a shipped arena's name or a path; a ConfigError naming
    ``file`` and ``key`` when there is none."""
    if is_arena_path(value):
        path = Path(value).expanduser()
        if not path.is_file():
            raise ConfigError(
                f"the arena file {path} does not exist",
                file=str(file) if file else None,
                key=key,
            )
        return path
    path = ARENA_DIRECTORY / f"{value}.yaml"
    if not path.is_file():
        raise ConfigError(
            f"unknown arena {value!r}; expected one of: {', '.join(shipped_arenas())}, "
            "or an arena file's path",
            file=str(file) if file else None,
            key=key,
        )
    return path


def load_arena(value: str | Path, *, file: str | Path | None = None) -> Arena:
    """The arena named ``value`` (shipped) or in the file ``value``; every fault is one
    ConfigError naming the arena file and the key (``file``: the experiment that named it)."""
    path = value if isinstance(value, Path) else arena_path(value, file=file)
    return decode(read_yaml(path), Arena, file=path)
