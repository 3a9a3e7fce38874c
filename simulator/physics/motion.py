"""One step of an arena (:func:`step_world`): every robot drives the exact arc of its constant
wheel speeds over the step, then robots and boxes are parted (:mod:`.contacts`, :mod:`.boxes`) in
rounds until nothing moves.
"""

from __future__ import annotations

import math

import numpy as np

from minimize_surprise.jit import kernel
from simulator.physics.boxes import _push_boxes
from simulator.physics.contacts import _separate_robots
from simulator.physics.model import _TWO_PI, Geometry

__all__ = ["clamp_commands", "step_world"]

# Rounds of robot separation and box pushing per step: a robot sent back to where it was by
# boxes may touch another robot again, which may push it into boxes again; most steps need one
# or two, jams of bladed robots among boxes up to five.
_CONTACT_ROUNDS = 6
_FOUR_PI = 2.0 * _TWO_PI


@kernel(inline=True)
def _wrap(theta: float) -> float:
    # (theta + pi) % 2 pi - pi with Python's floored modulo, to the bit, without its call to
    # fmod for an angle at most a turn out of range: fmod(x, 2 pi) is then x, or x - 2 pi
    # (exact for 2 pi <= x < 4 pi), and the modulo adds 2 pi to a negative one.
    x = theta + math.pi
    if 0.0 <= x < _TWO_PI:
        m = x
    elif _TWO_PI <= x < _FOUR_PI:
        m = x - _TWO_PI
    elif -_TWO_PI < x < 0.0:
        m = x + _TWO_PI
    else:
        m = x % _TWO_PI
    return m - math.pi


@kernel
def _move(g: Geometry, pose: np.ndarray, cmd: np.ndarray) -> None:
    dt = g.dt
    for i in range(pose.shape[0]):
        left, right = cmd[i, 0], cmd[i, 1]
        v = (left + right) * g.half_vmax
        dth = (right - left) * (g.vmax_over_base * dt)
        # The exact arc: a chord of length v dt sinc(dth / 2) along the mean heading.
        half = 0.5 * dth
        sinc = 1.0 if half == 0.0 else math.sin(half) / half
        chord = v * dt * sinc
        mid = pose[i, 2] + half
        pose[i, 0] += chord * math.cos(mid)
        pose[i, 1] += chord * math.sin(mid)
        pose[i, 2] = _wrap(pose[i, 2] + dth)


@kernel
def clamp_commands(commands: np.ndarray, cmd: np.ndarray) -> None:
    """``cmd`` = ``commands`` clamped to [-1, 1], NaN as 0 (a robot's wheels take no more)."""
    for i in range(cmd.shape[0]):
        for k in range(2):
            v = commands[i, k]
            cmd[i, k] = 0.0 if v != v else min(max(v, -1.0), 1.0)


@kernel
def step_world(
    g: Geometry, pose: np.ndarray, cmd: np.ndarray, force: np.ndarray,
    boxes: np.ndarray | None, pending: np.ndarray | None, first: int, last: int,
    need_force: bool, grid: bool | None,
) -> None:  # fmt: skip
    """Advance one arena by one step of ``g.dt`` with the commands ``cmd``; its boxes are rows
    ``first`` to ``last - 1`` of ``boxes`` and ``pending`` (a batch's boxes, one arena after
    the other).

    An arena without boxes passes None for ``boxes`` and ``pending``, and one of fewer robots
    than ``g.grid_robots`` None for ``grid`` (:func:`~simulator.physics.grid.grid_choice`):
    numba then compiles neither the box physics nor the grid (the branches are pruned by
    type), what a small swarm without boxes never runs; the steps taken are the same."""
    if boxes is None or pending is None:
        _move(g, pose, cmd)
        force[:] = 0.0
        _separate_robots(g, pose, grid)
    else:
        _step_with_boxes(
            g, pose, cmd, force, boxes[first:last], pending[first:last], need_force, grid
        )


@kernel
def _step_with_boxes(
    g: Geometry, pose: np.ndarray, cmd: np.ndarray, force: np.ndarray, boxes: np.ndarray,
    pending: np.ndarray, need_force: bool, grid: bool | None,
) -> None:  # fmt: skip
    # Where the robots were, for the boxes to send one back to (no copy without boxes).
    start = pose.copy() if boxes.shape[0] > 0 else pose
    _move(g, pose, cmd)
    force[:] = 0.0
    for round_ in range(_CONTACT_ROUNDS):
        # Robots part first, then boxes give way to them; a robot the boxes moved (backed off
        # or sent back) may touch another robot again, hence another round.
        parted = _separate_robots(g, pose, grid)
        if (round_ > 0 and not parted) or boxes.shape[0] == 0:
            break
        before = pose.copy()
        _push_boxes(g, pose, start, boxes, pending, force, need_force)
        same = True
        for i in range(pose.shape[0]):
            for k in range(3):
                if pose[i, k] != before[i, k]:
                    same = False
        if same:
            break
