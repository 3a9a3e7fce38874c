"""The horizontal IR sensors' two models, ``cone`` (Enki's Thymio II) and ``ray`` (Webots').

``cone``: the nearest body or visible wall within a cone of half angle ``ir_aperture`` gives
``c / (d^2 + c)`` below ``ir_range``; ``ray``: the first body or visible wall on the sensor's
axis, at its distance divided by its reflectance, looked up in a distance -> value table, with
Gaussian noise of ``ir_noise`` times the value.
"""

from __future__ import annotations

import math

import numpy as np

from minimize_surprise.jit import kernel
from simulator.physics.model import IR_HEADINGS, IR_POSITIONS, Sensing, gaussian

__all__ = ["IR_CONE", "IR_RAY", "ir_noise", "ir_readings"]

#: ``Sensing.ir_model`` values.
IR_CONE = 0
IR_RAY = 1

_IR_COS = np.cos(IR_HEADINGS)
_IR_SIN = np.sin(IR_HEADINGS)


@kernel(inline=True)
def _lookup(d: float, table_d: np.ndarray, table_v: np.ndarray) -> float:
    # Linear interpolation in the table; beyond its ends, its end values.
    if d <= table_d[0]:
        return table_v[0]
    last = table_d.shape[0] - 1
    if d >= table_d[last]:
        return table_v[last]
    k = 1
    while table_d[k] < d:
        k += 1
    f = (d - table_d[k - 1]) / (table_d[k] - table_d[k - 1])
    return table_v[k - 1] + f * (table_v[k] - table_v[k - 1])


@kernel(inline=True)
def ir_readings(
    sn: Sensing, bodies: np.ndarray, n: int, x: float, y: float, c: float, s: float,
    out: np.ndarray, row: int,
) -> None:  # fmt: skip
    """A robot's seven horizontal IR values before their noise (:func:`ir_noise`) into
    ``out[row, :7]`` (a row and an index, not a view: a view counts references), the robot at
    (x, y) with heading cosine and sine (c, s). ``bodies[:n]`` (N, 2): the centres of the other
    robots' body circles it may see (its neighbours; the nearest is the same in any order)."""
    # The model's numbers into locals once: the sensors below then call helpers of plain
    # numbers, a call with the whole Sensing costing more than a sensor's arithmetic (measured).
    r, ir_range, walls = sn.robot_radius, sn.ir_range, sn.walls_visible
    wall_x, wall_y = sn.wall_hx, sn.wall_hy
    # The table's arrays too: each read of an array from the tuple takes a reference (atomic).
    table_d, table_v = sn.ir_table_d, sn.ir_table_v
    reach2 = (ir_range + r) ** 2
    for k in range(7):
        px, py = IR_POSITIONS[k, 0], IR_POSITIONS[k, 1]
        sx = x + c * px - s * py
        sy = y + s * px + c * py
        # cos and sin of the heading plus the sensor's, from those of each
        cp = c * _IR_COS[k] - s * _IR_SIN[k]
        sp = s * _IR_COS[k] + c * _IR_SIN[k]
        if sn.ir_model == IR_CONE:
            ca, sa = sn.ir_ca, sn.ir_sa
            best = _cone_nearest(
                bodies, n, sx, sy, cp, sp, r, reach2, ca, sa, walls, wall_x, wall_y
            )
            out[row, k] = 0.0 if best >= ir_range else sn.ir_c / (best * best + sn.ir_c)
            continue
        best = _ray_nearest(
            bodies, n, sx, sy, cp, sp, r, reach2, sn.ir_robot_reflectance, walls, wall_x,
            wall_y, sn.ir_wall_reflectance,
        )  # fmt: skip
        if best >= ir_range:
            out[row, k] = 0.0
            continue
        out[row, k] = _lookup(best, table_d, table_v)


@kernel(inline=True)
def ir_noise(sn: Sensing, step: int, out: np.ndarray) -> None:
    """Every robot's IR noise at ``step`` on its values ``out[robot, :7]`` (:func:`ir_readings`):
    the ray model's, in proportion to a value above 0, a draw per sensor."""
    if sn.ir_model == IR_CONE or sn.ir_noise <= 0.0:
        return
    seed, noise = sn.seed, sn.ir_noise
    for i in range(out.shape[0]):
        for k in range(7):
            value = out[i, k]
            if value > 0.0:
                out[i, k] = value + noise * value * gaussian(seed, step, i, 32 + k)


@kernel(inline=True)
def _cone_nearest(
    bodies: np.ndarray, n: int, sx: float, sy: float, cp: float, sp: float, r: float,
    reach2: float, ca: float, sa: float, walls: bool, wall_x: float, wall_y: float,
) -> float:  # fmt: skip
    # The nearest body or visible wall within the cone of the sensor at (sx, sy) facing
    # (cp, sp), half angle with cosine and sine (ca, sa); inf if none.
    best = np.inf
    for j in range(n):
        wx = bodies[j, 0] - sx
        wy = bodies[j, 1] - sy
        if wx * wx + wy * wy >= reach2:
            continue  # out of range whatever the direction
        dot = wx * cp + wy * sp
        cross = abs(wx * sp - wy * cp)
        # The ray of the cone nearest the other body's centre: the axis if the centre is
        # inside the cone, else the cone's edge.
        perp = cross * ca - dot * sa
        centre = math.sqrt(wx * wx + wy * wy)
        if perp <= 0.0:
            along = centre
            perp = 0.0
        else:
            along = dot * ca + cross * sa
        chord2 = r * r - perp * perp
        if centre < r:
            d = 0.0
        elif chord2 > 0.0 and along > 0.0:
            d = along - math.sqrt(chord2)
        else:
            continue
        if d < best:
            best = d
    if walls:
        for k in range(4):
            if k == 0:
                cosn, sinn, gap = cp, abs(sp), wall_x - sx
            elif k == 1:
                cosn, sinn, gap = -cp, abs(sp), wall_x + sx
            elif k == 2:
                cosn, sinn, gap = sp, abs(cp), wall_y - sy
            else:
                cosn, sinn, gap = -sp, abs(cp), wall_y + sy
            eff = 1.0 if cosn >= ca else cosn * ca + sinn * sa
            if eff > 1e-9:
                d = max(gap, 0.0) / eff
                if d < best:
                    best = d
    return best


@kernel(inline=True)
def _ray_nearest(
    bodies: np.ndarray, n: int, sx: float, sy: float, cp: float, sp: float, r: float,
    reach2: float, robot_reflectance: float, walls: bool, wall_x: float, wall_y: float,
    wall_reflectance: float,
) -> float:  # fmt: skip
    # The first body or visible wall on the axis of the sensor at (sx, sy) facing (cp, sp), at
    # its distance divided by its reflectance; inf if none.
    best = np.inf
    for j in range(n):
        wx = bodies[j, 0] - sx
        wy = bodies[j, 1] - sy
        if wx * wx + wy * wy >= reach2:
            continue  # out of range whatever the direction
        along = wx * cp + wy * sp
        perp2 = wx * wx + wy * wy - along * along
        if wx * wx + wy * wy < r * r:
            d = 0.0
        elif along > 0.0 and perp2 < r * r:
            d = along - math.sqrt(r * r - perp2)
        else:
            continue
        d /= robot_reflectance
        if d < best:
            best = d
    if walls:
        d = np.inf
        if cp > 1e-12:
            d = min(d, max(wall_x - sx, 0.0) / cp)
        elif cp < -1e-12:
            d = min(d, max(wall_x + sx, 0.0) / -cp)
        if sp > 1e-12:
            d = min(d, max(wall_y - sy, 0.0) / sp)
        elif sp < -1e-12:
            d = min(d, max(wall_y + sy, 0.0) / -sp)
        d /= wall_reflectance
        if d < best:
            best = d
    return best
