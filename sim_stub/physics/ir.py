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
from sim_stub.physics.model import Sensing, gaussian

__all__ = ["IR_CONE", "IR_RAY"]

#: ``Sensing.ir_model`` values.
IR_CONE = 0
IR_RAY = 1


@kernel
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


@kernel
def _ir_value(
    sn: Sensing, bodies: np.ndarray, n: int, skip: int, me: int, sx: float, sy: float,
    cp: float, sp: float, step: int, channel: int,
) -> float:  # fmt: skip
    # Robot ``me``'s sensor at (sx, sy) facing (cp, sp). ``bodies[:n]`` (N, 2): the centres of
    # the other robots' body circles, and at row ``skip`` robot ``me``'s own (-1: not there):
    # every robot's, or those of its neighbours (.grid; the nearest is the same in any order).
    r = sn.robot_radius
    best = np.inf
    if sn.ir_model == IR_CONE:
        ca, sa = sn.ir_ca, sn.ir_sa
        reach2 = (sn.ir_range + r) ** 2
        for j in range(n):
            if j == skip:
                continue
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
        if sn.walls_visible:
            wall = sn.wall_half
            for k in range(4):
                if k == 0:
                    cosn, sinn, gap = cp, abs(sp), wall - sx
                elif k == 1:
                    cosn, sinn, gap = -cp, abs(sp), wall + sx
                elif k == 2:
                    cosn, sinn, gap = sp, abs(cp), wall - sy
                else:
                    cosn, sinn, gap = -sp, abs(cp), wall + sy
                eff = 1.0 if cosn >= ca else cosn * ca + sinn * sa
                if eff > 1e-9:
                    d = max(gap, 0.0) / eff
                    if d < best:
                        best = d
        if best >= sn.ir_range:
            return 0.0
        return sn.ir_c / (best * best + sn.ir_c)
    # The ray model: the first body or visible wall on the axis.
    reach2 = (sn.ir_range + r) ** 2
    for j in range(n):
        if j == skip:
            continue
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
        d /= sn.ir_robot_reflectance
        if d < best:
            best = d
    if sn.walls_visible:
        wall = sn.wall_half
        d = np.inf
        if cp > 1e-12:
            d = min(d, max(wall - sx, 0.0) / cp)
        elif cp < -1e-12:
            d = min(d, max(wall + sx, 0.0) / -cp)
        if sp > 1e-12:
            d = min(d, max(wall - sy, 0.0) / sp)
        elif sp < -1e-12:
            d = min(d, max(wall + sy, 0.0) / -sp)
        d /= sn.ir_wall_reflectance
        if d < best:
            best = d
    if best >= sn.ir_range:
        return 0.0
    value = _lookup(best, sn.ir_table_d, sn.ir_table_v)
    if value > 0.0 and sn.ir_noise > 0.0:
        value += sn.ir_noise * value * gaussian(sn.seed, step, me, 32 + channel)
    return value
