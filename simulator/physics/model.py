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
from simulator.physics.grid import GRID_ROBOTS

__all__ = [
    "GROUND_POSITIONS",
    "IR_HEADINGS",
    "IR_POSITIONS",
    "Geometry",
    "Sensing",
    "gaussian",
    "normal_quantile",
]

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
    #: the larger of the walls' half extents: the neighbour grids' square spans it
    wall_half: float
    #: the walls' half extents along x and y (the walls are a rectangle around the centre)
    wall_hx: float
    wall_hy: float
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
    wall_half: float  # as Geometry's: the grids'
    wall_hx: float
    wall_hy: float
    robot_radius: float
    body_offset: float
    #: the carpet's half extents along x and y
    arena_hx: float
    arena_hy: float
    ground_carpet: float
    ground_outside: float
    ground_noise: float
    light: bool
    light_centre: float
    #: the point under the lamp
    light_x: float
    light_y: float
    light_exponent: float
    lamp_h2: float
    light_uniform: float
    light_offsets: np.ndarray  # (2, 2) in the robot's frame
    noise: float
    columns: np.ndarray
    seed: int
    #: the farthest apart two body centres are when one robot's IR sees the other
    #: (.sensing.ir_reach of robot_radius, body_offset and ir_range: a Sensing that changes one
    #: of them changes this too, or the IR misses bodies it should see)
    ir_reach: float
    #: from this many robots on, the IR finds the robots it may see in a cell grid (.grid)
    grid_robots: int = GRID_ROBOTS


# --------------------------------------------------------------------------- random numbers


#: Wichura's algorithm AS 241 (PPND16, Applied Statistics 37, 1988): rational functions for the
#: centre, |p - 1/2| <= 0.425, and of sqrt(-log(p)) for the tails, numerator and denominator
#: coefficients from the highest power down.
_CENTRE_NUM = (
    2509.0809287301226727, 33430.575583588128105, 67265.770927008700853, 45921.953931549871457,
    13731.693765509461125, 1971.5909503065514427, 133.14166789178437745, 3.387132872796366608,
)  # fmt: skip
_CENTRE_DEN = (
    5226.495278852545925, 28729.085735721942674, 39307.89580009271061, 21213.794301586595867,
    5394.1960214247511077, 687.1870074920579083, 42.313330701600911252, 1.0,
)  # fmt: skip
_NEAR_NUM = (
    7.7454501427834140764e-4, 0.0227238449892691845833, 0.24178072517745061177,
    1.27045825245236838258, 3.64784832476320460504, 5.7694972214606914055,
    4.6303378461565452959, 1.42343711074968357734,
)  # fmt: skip
_NEAR_DEN = (
    1.05075007164441684324e-9, 5.475938084995344946e-4, 0.0151986665636164571966,
    0.14810397642748007459, 0.68976733498510000455, 1.6763848301838038494,
    2.05319162663775882187, 1.0,
)  # fmt: skip
_FAR_NUM = (
    2.01033439929228813265e-7, 2.71155556874348757815e-5, 0.0012426609473880784386,
    0.026532189526576123093, 0.29656057182850489123, 1.7848265399172913358,
    5.4637849111641143699, 6.6579046435011037772,
)  # fmt: skip
_FAR_DEN = (
    2.04426310338993978564e-15, 1.4215117583164458887e-7, 1.8463183175100546818e-5,
    7.868691311456132591e-4, 0.0148753612908506148525, 0.13692988092273580531,
    0.59983220655588793769, 1.0,
)  # fmt: skip


@kernel(inline=True)
def _ratio(x: float, num: tuple[float, ...], den: tuple[float, ...]) -> float:
    # num(x) / den(x), both of degree 7, by Horner's rule.
    p = num[0]
    q = den[0]
    for k in range(1, 8):
        p = p * x + num[k]
        q = q * x + den[k]
    return p / q


@kernel(inline=True)
def normal_quantile(p: float) -> float:
    """The standard normal distribution's quantile of ``p`` in (0, 1), to about 1e-16 relative
    (Wichura's AS 241); most ``p`` take the centre's rational function alone, no logarithm."""
    q = p - 0.5
    if abs(q) <= 0.425:
        return q * _ratio(0.180625 - q * q, _CENTRE_NUM, _CENTRE_DEN)
    r = math.sqrt(-math.log(p if q < 0.0 else 1.0 - p))
    if r <= 5.0:
        value = _ratio(r - 1.6, _NEAR_NUM, _NEAR_DEN)
    else:
        value = _ratio(r - 5.0, _FAR_NUM, _FAR_DEN)
    return -value if q < 0.0 else value


@kernel
def gaussian(seed: int, step: int, robot: int, channel: int) -> float:
    """A standard normal number for (seed, step, robot, channel), the same on every call: the
    normal quantile (:func:`normal_quantile`) of a uniform number hashed from the four, one of
    the 2^32 midpoints (k + 1/2) / 2^32. Cheaper than the Box-Muller transform with its
    logarithm and cosine, since most draws call no libm function (docs/simulation.md)."""
    key = mix32(seed ^ mix32(step ^ mix32(robot * 64 + channel)))
    return normal_quantile((mix32(key ^ 0x9E3779B9) + 0.5) / 4294967296.0)
