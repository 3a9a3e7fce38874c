"""The simulated worlds: every parameter of the arena, the robots and their sensors, and the named
scenarios of the paper (Sec. V) that set them.

A scenario is a set of defaults; an experiment overrides any of them by name through its
``simulation`` mapping, e.g. ``{"arena_side": 0.8, "noise": 0.02}``. Lengths are in metres, angles
in degrees, times in seconds, sensor values normalised to [0, 1] as the real drivers deliver them.

Coordinates: the origin is the centre of the carpet, x to the right, y up; the carpet covers
``[-arena_side / 2, arena_side / 2]`` on both axes and the walls stand ``wall_margin`` further out.
A robot's pose is the point between its wheels and its heading (the Thymio II's geometry: wheels
9.4 cm apart, the body's front arc 8 cm ahead of the wheel axis and its flat rear 3 cm behind it;
see :class:`WorldConfig`).
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec

from minimize_surprise.config import Strict, decode
from minimize_surprise.errors import ConfigError
from minimize_surprise.sensors import (
    ALL_SENSORS,
    FORCE_SENSORS,
    GROUND_SENSORS,
    IR_SENSORS,
    LIGHT_SENSORS,
    check_sensor_names,
)
from simulator.arenas import Arena, load_arena

Positive = Annotated[float, msgspec.Meta(gt=0.0)]
NonNegative = Annotated[float, msgspec.Meta(ge=0.0)]
Unit = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
Point = tuple[float, float]
#: (x0, y0, x1, y1): a rectangle in the arena's frame, x0 < x1 and y0 < y1
Region = tuple[float, float, float, float]
#: (x, y, heading in degrees counter-clockwise from the x axis): a robot's pose
Pose = tuple[float, float, float]


class WorldConfig(Strict, frozen=True):
    """Every parameter of a simulated world (see the module docstring for units and axes).

    The robots approximate the Thymio II body (front arc of radius 8 cm around the wheel axis, flat
    rear 3 cm behind it, 11 cm wide) by a circle of ``robot_radius`` whose centre lies
    ``body_offset`` ahead of the wheel axis; the IR sensors, collisions and clusters use it. Robots
    that carry the ``force`` sensor also carry the pushing blade, a bar across their front.
    """

    # --- arena -------------------------------------------------------------------------------
    #: the carpet's extent along x (its side, for a square carpet)
    arena_side: Positive = 1.0
    #: the carpet's extent along y (``None``: ``arena_side``, a square)
    arena_height: Positive | None = None
    #: distance from the carpet's edge out to the walls
    wall_margin: NonNegative = 0.1
    #: whether the horizontal IR sensors see the walls (the paper's basic arenas: low walls, no)
    walls_visible_to_ir: bool = False
    # --- robots ------------------------------------------------------------------------------
    #: number of robots (in an experiment the experiment's ``robots`` replaces it)
    robots: Annotated[int, msgspec.Meta(ge=1)] = 10
    #: wheel speed for a normalised command of 1: the real robots' 10.6 cm/s (the drivers' speed
    #: scale of 265 motor units); the paper setting's Webots robots drive 12.6 cm/s
    max_speed: Positive = 0.106
    #: distance between the wheels (Thymio II: 9.4 cm)
    wheel_base: Positive = 0.094
    #: length of one step (in an experiment its ``step_period``: the world steps once per control
    #: step; a value given here must equal it)
    dt: Positive = 0.1
    #: "random": seeded, non-overlapping poses on the carpet (or in ``start_region``); "centre":
    #: fixed ring at the centre; "fixed": the poses ``start_poses``
    start: Literal["random", "centre", "fixed"] = "random"
    #: "random" start: the rectangle the robots' bodies start in (``None``: the whole carpet)
    start_region: Region | None = None
    #: "fixed" start: one (x, y, heading in degrees) per robot, the point between its wheels
    start_poses: tuple[Pose, ...] = ()
    #: "centre" start: distance of the wheel axes from the centre (``None``: neighbours just
    #: apart); every robot faces outwards
    start_ring: NonNegative | None = None
    #: "centre" start: the direction of the first robot from the centre, in degrees
    start_ring_phase: float = 45.0
    #: free space kept between robots (and between boxes and robots) when placing them
    start_clearance: NonNegative = 0.02
    #: radius of the circle standing for a robot's body (11 cm wide, 11.2 cm long)
    robot_radius: Positive = 0.058
    #: how far ahead of the wheel axis that circle's centre lies (front arc 8 cm, rear 3 cm)
    body_offset: float = 0.025
    #: the blade (robots with a force sensor): its centre line ahead of the wheel axis
    blade_x: Positive = 0.09
    #: the blade's width across the robot
    blade_width: Positive = 0.12
    #: the blade's thickness
    blade_thickness: Positive = 0.01
    #: what the robots carry, in the order :meth:`World.sensor_values` returns them
    sensors: tuple[str, ...] = IR_SENSORS + GROUND_SENSORS
    # --- sensor models -----------------------------------------------------------------------
    #: standard deviation of the Gaussian noise added to every normalised value (then clipped)
    noise: NonNegative = 0.0
    #: "cone": the nearest body within a cone, c / (d^2 + c) (Enki's Thymio II, the real robots);
    #: "ray": the first body on the sensor's axis, looked up in ``ir_table`` (Webots' Thymio II)
    ir_model: Literal["cone", "ray"] = "cone"
    #: nothing is seen from this distance on
    ir_range: Positive = 0.14
    #: half opening angle of the IR cone (Enki's Thymio model: 15 degrees)
    ir_aperture: Annotated[float, msgspec.Meta(ge=0.0, lt=90.0)] = 15.0
    #: shape of the IR response c / (d^2 + c), in m^2 (Enki's Thymio model: 73 cm^2); 1 at contact
    ir_response_c: Positive = 0.0073
    #: the ray model's (distance in m, normalised value) pairs, distances increasing
    ir_table: tuple[tuple[float, float], ...] = ((0.0, 1.0), (0.14, 0.0))
    #: the ray model's Gaussian noise, as a fraction of the value (0 when nothing is seen)
    ir_noise: NonNegative = 0.0
    #: the ray model: how well robots reflect the IR (Webots: a distance d reads as
    #: d / reflectance; a white body about 0.96)
    ir_robot_reflectance: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 1.0
    #: the ray model: how well the walls reflect the IR (as ``ir_robot_reflectance``)
    ir_wall_reflectance: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 1.0
    #: ground sensors over the carpet (Thymio ``prox.ground.reflected`` / 1023 on dark carpet)
    ground_carpet: Unit = 0.4
    #: ground sensors beyond the carpet's edge (bright boundary, above the safety limit of 0.55)
    ground_outside: Unit = 0.95
    #: Gaussian noise of the ground sensors as a fraction of the value (Webots: 1 %; 0 stays 0)
    ground_noise: NonNegative = 0.0
    #: force value per pushed box (paper: about 0.25 for 10 boxes); the value saturates at 1
    force_per_box: NonNegative = 0.025
    # --- boxes -------------------------------------------------------------------------------
    #: whether the carpet holds boxes to push
    boxes: bool = False
    #: fraction of the carpet covered by boxes (paper: about 14 %, 220 boxes per square metre)
    box_coverage: Annotated[float, msgspec.Meta(ge=0.0, le=0.4)] = 0.14
    #: number of boxes, instead of ``box_coverage`` ("random" layout)
    box_number: Annotated[int, msgspec.Meta(ge=0)] | None = None
    #: "random" layout: the rectangle the boxes are scattered in (``None``: the whole carpet);
    #: ``box_coverage`` is then of this rectangle's area
    box_region: Region | None = None
    #: a box's mass in kg (the Playground's boxes; the kinematic simulator's boxes move with
    #: whatever pushes them)
    box_mass: Positive = 0.01
    #: side of a (cubic) box
    box_size: Positive = 0.025
    #: "random": uniformly scattered to ``box_coverage``; "grid": the authors' Webots layout,
    #: rows ``box_grid_pitch`` apart, each box ``box_grid_pitch`` to ``+ box_grid_jitter`` after
    #: the last and up to ``box_grid_jitter`` off its row, all on a 1 cm raster
    box_layout: Literal["random", "grid"] = "random"
    #: "grid" layout: distance between rows, and the least distance between neighbours in a row
    box_grid_pitch: Positive = 0.054
    #: "grid" layout: the most a box lies beyond ``box_grid_pitch`` from the last and off its row
    box_grid_jitter: NonNegative = 0.018
    #: side of a square around the centre kept free of boxes at the start (the authors: 0.5 m)
    box_clear_centre: NonNegative = 0.0
    #: at most this many relaxation passes per step when boxes push each other
    box_iterations: Annotated[int, msgspec.Meta(ge=1)] = 12
    # --- light -------------------------------------------------------------------------------
    #: a light above the carpet (gradient arena); otherwise the light is uniform
    light: bool = False
    #: the point under the lamp
    light_position: Point = (0.0, 0.0)
    #: light value under the lamp: the value is ``light_centre * (h^2 / (h^2 +
    #: r^2))^light_exponent`` at a distance r from the point under the lamp, h fixed by the corner
    #: value
    light_centre: Unit = 1.0
    #: light value at the carpet's corners, or for a lamp not above the centre, at the distance
    #: of the corners from the centre
    light_corner: Unit = 0.1
    #: how the light falls off (1: inverse square; 1.5: inverse square on a sensor facing up)
    light_exponent: Annotated[float, msgspec.Meta(gt=0.0, le=3.0)] = 1.0
    #: light value everywhere when ``light`` is false
    light_uniform: Unit = 0.5
    #: where L0 (left) and L1 (right) sit on the robot, in the robot's frame
    light_sensor_offsets: tuple[Point, Point] = ((0.0, 0.03), (0.0, -0.03))

    def __post_init__(self) -> None:
        try:
            check_sensor_names(self.sensors)
        except ValueError as exc:
            raise ValueError(f"`sensors`: {exc}") from None
        if not self.sensors:
            raise ValueError("`sensors`: at least one sensor is needed")
        if self.light and self.light_corner >= self.light_centre:
            raise ValueError("`light_corner`: must be below light_centre")
        if self.box_size >= min(self.carpet_width, self.carpet_height):
            raise ValueError("`box_size`: must be smaller than the arena")
        half_w, half_h = self.carpet_width / 2, self.carpet_height / 2
        for key, region in (("start_region", self.start_region), ("box_region", self.box_region)):
            if region is None:
                continue
            x0, y0, x1, y1 = region
            if not (x0 < x1 and y0 < y1):
                raise ValueError(f"`{key}`: expected x0 < x1 and y0 < y1, got {list(region)}")
            if x0 < -half_w or x1 > half_w or y0 < -half_h or y1 > half_h:
                raise ValueError(
                    f"`{key}`: {list(region)} reaches beyond the carpet "
                    f"({self.carpet_width} x {self.carpet_height} m around the centre)"
                )
        if self.start == "fixed" and len(self.start_poses) != self.robots:
            raise ValueError(
                f"`start_poses`: {len(self.start_poses)} poses for {self.robots} robots; a "
                "fixed start needs one per robot"
            )
        distances = [d for d, _ in self.ir_table]
        if len(distances) < 2 or any(b <= a for a, b in itertools.pairwise(distances)):
            raise ValueError("`ir_table`: at least two rows, distances strictly increasing")
        if any(not 0.0 <= v <= 1.0 for _, v in self.ir_table):
            raise ValueError("`ir_table`: values must lie in [0, 1]")

    @property
    def has_blade(self) -> bool:
        """Whether the robots carry the pushing blade (those with a force sensor do)."""
        return "force" in self.sensors

    @property
    def carpet_width(self) -> float:
        """The carpet's extent along x."""
        return self.arena_side

    @property
    def carpet_height(self) -> float:
        """The carpet's extent along y."""
        return self.arena_side if self.arena_height is None else self.arena_height

    @property
    def wall_hx(self) -> float:
        """Distance from the centre to the walls left and right."""
        return self.arena_side / 2 + self.wall_margin

    @property
    def wall_hy(self) -> float:
        """Distance from the centre to the walls above and below."""
        return self.carpet_height / 2 + self.wall_margin

    @property
    def wall_half(self) -> float:
        """Distance from the centre to the farther walls (to every wall on a square carpet)."""
        return max(self.wall_hx, self.wall_hy)

    @property
    def box_area(self) -> float:
        """The area the boxes are scattered over: ``box_region``'s or the carpet's."""
        if self.box_region is not None:
            x0, y0, x1, y1 = self.box_region
            return (x1 - x0) * (y1 - y0)
        if self.arena_height is None:
            return self.arena_side**2
        return self.arena_side * self.arena_height

    @property
    def box_count(self) -> int:
        """Number of boxes for the configured coverage of the carpet (0 without boxes)."""
        if not self.boxes:
            return 0
        if self.box_number is not None:
            return self.box_number
        return round(self.box_coverage * self.box_area / self.box_size**2)


_OBJECT_SENSORS = IR_SENSORS + GROUND_SENSORS + FORCE_SENSORS

#: The named scenarios: each an arena (simulator/arenas/NAME.yaml) and its robots: how many and
#: what they carry.
_SCENARIOS: dict[str, dict[str, Any]] = {
    # Paper Sec. V-B: 10 Thymios with 7 IR and 2 ground sensors.
    "basic": {"arena": "basic", "robots": 10},
    # Paper Sec. V-C: 4 extended Thymios with the blade and its force sensor.
    "boxes": {"arena": "boxes", "robots": 4, "sensors": list(_OBJECT_SENSORS)},
    # As "boxes" with the two light sensors.
    "gradient": {
        "arena": "gradient",
        "robots": 4,
        "sensors": list(_OBJECT_SENSORS + LIGHT_SENSORS),
    },
}

#: Names accepted by :func:`scenario_config`.
SCENARIOS: tuple[str, ...] = tuple(_SCENARIOS)

assert all(set(s.get("sensors", ())) <= set(ALL_SENSORS) for s in _SCENARIOS.values())


class _Document(Strict, frozen=True):
    # Wrapping the world in a ``simulation`` key makes decode() report keys as the experiment
    # configuration spells them, e.g. "simulation.arena_side".
    simulation: WorldConfig


def scenario_arena(name: str) -> str:
    """The name of scenario ``name``'s own arena (``KeyError`` for an unknown scenario)."""
    return str(_SCENARIOS[name]["arena"])


def scenario_config(
    name: str,
    overrides: dict[str, Any] | None = None,
    *,
    file: str | Path | None = None,
    arena: Arena | None = None,
) -> WorldConfig:
    """The world of scenario ``name`` with ``overrides`` (field name to value) applied.

    The world is the scenario's robots in ``arena`` (default: the scenario's own), then the
    overrides. Raises :class:`~minimize_surprise.errors.ConfigError` for an unknown scenario
    (key ``scenario``) or a bad override (key ``simulation.<field>``); ``file`` is named in the
    error.
    """
    if name not in _SCENARIOS:
        raise ConfigError(
            f"unknown scenario {name!r}; expected one of: {', '.join(SCENARIOS)}",
            file=str(file) if file else None,
            key="scenario",
        )
    if overrides is not None and not isinstance(overrides, dict):
        raise ConfigError(
            "expected a mapping of world parameters",
            file=str(file) if file else None,
            key="simulation",
        )
    robots = {k: v for k, v in _SCENARIOS[name].items() if k != "arena"}
    if arena is None:
        arena = load_arena(scenario_arena(name))
    merged = {**robots, **arena.world(), **(overrides or {})}
    return decode({"simulation": merged}, _Document, file=file).simulation
