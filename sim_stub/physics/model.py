"""What every part of the arena's physics shares: the world's constants as the kernels take
them (:class:`Geometry`, :class:`Sensing`), the Thymio II's sensor geometry and the noise
generator (:func:`gaussian`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from minimize_surprise.jit import kernel
from minimize_surprise.rng import mix32
from sim_stub.physics.grid import GRID_ROBOTS

__all__ = ["GROUND_POSITIONS", "IR_HEADINGS", "IR_POSITIONS", "Geometry", "Sensing", "gaussian"]

# Thymio II sensor geometry (docs/simulation.md, from Enki's model), metres and radians, robot
# frame: x forward, y left, origin between the wheels.
IR_POSITIONS = np.array(
    [
        [0.062, 0.0485],
        [0.075, 0.0255],
        [0.0795, 0.0],
        [0.075, -0.0255],
        [0.062, -0.0485],
        [-0.0295, 0.0295],
        [-0.0295, -0.0295],
    ]
)
IR_HEADINGS = np.radians([40.0, 20.0, 0.0, -20.0, -40.0, 180.0, 180.0])
GROUND_POSITIONS = np.array([[0.072, 0.012], [0.072, -0.012]])

_TWO_PI = 2.0 * math.pi


class Geometry(NamedTuple):
    """The constants of a world's motion and contacts (metres, seconds; see WorldConfig)."""

    dt: float
    half_vmax: float
    vmax_over_base: float
    robot_radius: float
    body_offset: float
    wall_half: float
    blade: bool
    blade_x: float
    blade_width: float
    hw: float  # half the blade's width
    tb: float  # half the blade's thickness
    hull_x0: float  # the outline boxes meet on a bladed robot: core x0..x1, -hy..hy, grown by rr
    hull_x1: float
    hull_hy: float
    hull_rr: float
    rb: float  # a box's radius
    box_size: float
    box_iterations: int
    box_reach2: float  # boxes farther than this (squared) from a wheel axis cannot touch it
    force_per_box: float
    #: from this many robots on, contacts find neighbours in a cell grid (.grid)
    grid_robots: int = GRID_ROBOTS


class Sensing(NamedTuple):
    """The constants of a world's sensors; ``columns`` picks the world's sensors from the full
    frame of 12 (minimize_surprise.sensors.ALL_SENSORS) in the configured order."""

    need_ir: bool
    need_ground: bool
    need_force: bool
    need_light: bool
    ir_model: int
    ir_range: float
    ir_ca: float  # cos and sin of the cone's half angle
    ir_sa: float
    ir_c: float
    ir_table_d: np.ndarray  # the ray model's distances (increasing) and values
    ir_table_v: np.ndarray
    ir_noise: float
    ir_robot_reflectance: float
    ir_wall_reflectance: float
    walls_visible: bool
    wall_half: float
    robot_radius: float
    body_offset: float
    arena_half: float
    ground_carpet: float
    ground_outside: float
    ground_noise: float
    light: bool
    light_centre: float
    light_exponent: float
    lamp_h2: float
    light_uniform: float
    light_offsets: np.ndarray  # (2, 2) in the robot's frame
    noise: float
    columns: np.ndarray
    seed: int
    #: the farthest apart two body centres are when one robot's IR sees the other
    #: (.sensing.ir_reach)
    ir_reach: float
    #: from this many robots on, the IR finds the robots it may see in a cell grid (.grid)
    grid_robots: int = GRID_ROBOTS


# --------------------------------------------------------------------------- random numbers


@kernel
def gaussian(seed: int, step: int, robot: int, channel: int) -> float:
    """A standard normal number for (seed, step, robot, channel), the same on every call."""
    key = mix32(seed ^ mix32(step ^ mix32(robot * 64 + channel)))
    u1 = (mix32(key ^ 0x9E3779B9) + 0.5) / 4294967296.0
    u2 = (mix32(key ^ 0x85EBCA6B) + 0.5) / 4294967296.0
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(_TWO_PI * u2)
