"""The arena's physics and sensors as compiled kernels (docs/simulation.md).

Every function here is a :func:`minimize_surprise.jit.kernel`: loops over robots and boxes on plain
arrays, compiled by numba. :class:`~sim_stub.world.World` calls them one step at a time (the
simulated robots of ``surprise-master sim --engine agents``); the engine (:mod:`sim_stub.engine`)
calls them from its own compiled evaluation loop. One implementation, so both give the same
trajectories bit for bit.

State of one arena (arrays the caller owns): ``pose`` (N, 3) x, y, theta of each robot's wheel
axis centre; ``cmd`` (N, 2) normalised wheel speeds; ``force`` (N,) this step's force value;
``boxes`` (B, 2) box centres; ``pending`` (B,) boxes that may still overlap something. The
constants of a world are in a :class:`Geometry` and a :class:`Sensing` (see
:func:`sim_stub.world.compile_world`).

Models:

* Motion: the exact arc of constant wheel speeds over one step.
* Contacts, each step: robots push each other apart (half each) and are kept inside the walls;
  then robots push boxes and boxes push boxes, the box farther down a pushing chain giving way. A
  box held by a wall, or wedged between a robot and other boxes, cannot give way: the robot
  pushing it backs off instead. A robot still wedged among boxes stays where it was before the
  step and the boxes settle around it. Overlaps shallower than 10 um are left alone.
* Force: ``force_per_box`` for each box the robot's blade moved this step, directly or through a
  chain of boxes, capped at 1.
* Horizontal IR, two models: ``cone`` (Enki's Thymio II, the real robots' calibration): the
  nearest body or visible wall within a cone of half angle ``ir_aperture`` gives ``c / (d^2 + c)``
  below ``ir_range``; ``ray`` (Webots' Thymio II, the paper's simulation): the first body or
  visible wall on the sensor's axis, at its distance divided by its reflectance
  (``ir_robot_reflectance``, ``ir_wall_reflectance``), looked up in a distance -> value table,
  with Gaussian noise of ``ir_noise`` times the value.
* Ground: ``ground_carpet`` over the carpet, ``ground_outside`` beyond its edge, with Gaussian
  noise of ``ground_noise`` times the value.
* Light: a lamp's fall-off ``centre * (h^2 / (h^2 + r^2))^light_exponent`` from ``light_centre``
  under it to ``light_corner`` at the carpet's corners, or ``light_uniform`` everywhere.
* Noise: Gaussian ``noise`` on every value, from a counter-based generator keyed by (seed, step,
  robot, sensor), so a value never depends on who reads it when; then clipped to [0, 1].
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from minimize_surprise.jit import kernel
from minimize_surprise.rng import mix32

__all__ = [
    "GROUND_POSITIONS",
    "IR_CONE",
    "IR_HEADINGS",
    "IR_POSITIONS",
    "IR_RAY",
    "Geometry",
    "Sensing",
    "gaussian",
    "sense",
    "step_world",
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
_IR_COS = np.cos(IR_HEADINGS)
_IR_SIN = np.sin(IR_HEADINGS)
GROUND_POSITIONS = np.array([[0.072, 0.012], [0.072, -0.012]])

#: ``Sensing.ir_model`` values.
IR_CONE = 0
IR_RAY = 1

# Indices of the sensors in the full frame (minimize_surprise.sensors.ALL_SENSORS).
_IR0, _GROUND0, _FORCE, _LIGHT0 = 0, 7, 9, 10

_TWO_PI = 2.0 * math.pi
# Overlaps shallower than this (metres) are left alone: resolving them exactly would take many
# more passes for nothing anyone could measure (boxes and robots are a few centimetres).
_SLOP = 1e-5
# At most this many passes of robot-robot separation per step (most steps need none or one;
# pile-ups of several robots against a wall need more).
_ROBOT_PASSES = 8
# Rounds of settling boxes around robots wedged among them.
_SETTLE_ROUNDS = 3
# Rounds of robot separation and box pushing per step: a robot sent back to where it was by
# boxes may touch another robot again, which may push it into boxes again; most steps need one
# or two, jams of bladed robots among boxes up to five.
_CONTACT_ROUNDS = 6


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


# --------------------------------------------------------------------------- random numbers


@kernel
def gaussian(seed: int, step: int, robot: int, channel: int) -> float:
    """A standard normal number for (seed, step, robot, channel), the same on every call."""
    key = mix32(seed ^ mix32(step ^ mix32(robot * 64 + channel)))
    u1 = (mix32(key ^ 0x9E3779B9) + 0.5) / 4294967296.0
    u2 = (mix32(key ^ 0x85EBCA6B) + 0.5) / 4294967296.0
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(_TWO_PI * u2)


# --------------------------------------------------------------------------- motion and robots


@kernel
def _wrap(theta: float) -> float:
    return (theta + math.pi) % _TWO_PI - math.pi


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
def _wall_shift(g: Geometry, x: float, y: float, c: float, s: float) -> tuple[float, float]:
    # Translation that brings a robot's body (and blade) back inside the walls.
    wall = g.wall_half
    r = g.robot_radius
    cx = x + g.body_offset * c
    cy = y + g.body_offset * s
    lo_x = r - wall - cx
    hi_x = cx - (wall - r)
    lo_y = r - wall - cy
    hi_y = cy - (wall - r)
    if g.blade:
        ax = x + g.blade_x * c - g.hw * s
        ay = y + g.blade_x * s + g.hw * c
        bx = ax + 2 * g.hw * s
        by = ay - 2 * g.hw * c
        tb = g.tb
        lo_x = max(lo_x, tb - wall - ax, tb - wall - bx)
        hi_x = max(hi_x, ax - (wall - tb), bx - (wall - tb))
        lo_y = max(lo_y, tb - wall - ay, tb - wall - by)
        hi_y = max(hi_y, ay - (wall - tb), by - (wall - tb))
    return max(lo_x, 0.0) - max(hi_x, 0.0), max(lo_y, 0.0) - max(hi_y, 0.0)


@kernel
def _keep_inside_walls(g: Geometry, pose: np.ndarray) -> None:
    for i in range(pose.shape[0]):
        c, s = math.cos(pose[i, 2]), math.sin(pose[i, 2])
        sx, sy = _wall_shift(g, pose[i, 0], pose[i, 1], c, s)
        pose[i, 0] += sx
        pose[i, 1] += sy


@kernel
def _separate_robots(g: Geometry, pose: np.ndarray) -> bool:
    # Whether any robot moved. Each pass computes every push from the same positions, then
    # applies them all, as a simultaneous relaxation.
    n = pose.shape[0]
    moved = False
    c = np.empty(n)
    s = np.empty(n)
    for i in range(n):
        c[i] = math.cos(pose[i, 2])
        s[i] = math.sin(pose[i, 2])
    r2 = 2 * g.robot_radius
    shift_x = np.empty(n)
    shift_y = np.empty(n)
    cx = np.empty(n)
    cy = np.empty(n)
    reach = g.robot_radius + g.tb
    for _ in range(_ROBOT_PASSES):
        shift_x[:] = 0.0
        shift_y[:] = 0.0
        for i in range(n):
            cx[i] = pose[i, 0] + g.body_offset * c[i]
            cy[i] = pose[i, 1] + g.body_offset * s[i]
        for i in range(n):
            for j in range(n):
                if i == j:
                    continue
                dx = cx[i] - cx[j]
                dy = cy[i] - cy[j]
                d2 = dx * dx + dy * dy
                if d2 < (r2 - _SLOP) ** 2:
                    if d2 < 1e-18:  # the same spot: part along x
                        dx, dy, d2 = (1.0 if i > j else -1.0), 0.0, 1.0
                    d = math.sqrt(d2)
                    # Each of two touching robots gives way by half the overlap.
                    k = 0.5 * (r2 - d) / d
                    shift_x[i] += k * dx
                    shift_y[i] += k * dy
        if g.blade:
            # Robot i's blade against robot j's body; both give way by half.
            for i in range(n):
                ax = pose[i, 0] + g.blade_x * c[i] - g.hw * s[i]
                ay = pose[i, 1] + g.blade_x * s[i] + g.hw * c[i]
                ux = 2 * g.hw * s[i]
                uy = -2 * g.hw * c[i]
                for j in range(n):
                    if i == j:
                        continue
                    wx = cx[j] - ax
                    wy = cy[j] - ay
                    t = (wx * ux + wy * uy) / (g.blade_width * g.blade_width)
                    t = min(max(t, 0.0), 1.0)
                    dx = wx - t * ux
                    dy = wy - t * uy
                    d2 = dx * dx + dy * dy
                    if d2 < (reach - _SLOP) ** 2:
                        d = math.sqrt(max(d2, 1e-18))
                        k = 0.5 * (reach - d) / d
                        shift_x[j] += k * dx
                        shift_y[j] += k * dy
                        shift_x[i] -= k * dx
                        shift_y[i] -= k * dy
        any_shift = False
        for i in range(n):
            pose[i, 0] += shift_x[i]
            pose[i, 1] += shift_y[i]
            sx, sy = _wall_shift(g, pose[i, 0], pose[i, 1], c[i], s[i])
            pose[i, 0] += sx
            pose[i, 1] += sy
            if shift_x[i] != 0.0 or shift_y[i] != 0.0 or sx != 0.0 or sy != 0.0:
                any_shift = True
        if not any_shift:
            return moved
        moved = True
    return moved


# --------------------------------------------------------------------------- boxes


@kernel
def _robot_box(
    g: Geometry, bx: float, by: float, x: float, y: float, c: float, s: float
) -> tuple[float, float, float, bool]:
    # Push (x, y) that moves a box out of a robot, the depth of the overlap (0: apart) and
    # whether the blade's front did it.
    if not g.blade:
        reach = g.robot_radius + g.rb
        dx = bx - (x + g.body_offset * c)
        dy = by - (y + g.body_offset * s)
        d2 = dx * dx + dy * dy
        if d2 >= (reach - _SLOP) ** 2:
            return 0.0, 0.0, 0.0, False
        d = math.sqrt(max(d2, 1e-18))
        depth = reach - d
        return depth * dx / d, depth * dy / d, depth, False
    # With a blade, boxes meet one convex outline: a rectangle with rounded corners from the
    # flat rear to the blade's front face, as wide as the blade.
    x0, x1, hy, rr = g.hull_x0, g.hull_x1, g.hull_hy, g.hull_rr
    dx = bx - x
    dy = by - y
    lx = dx * c + dy * s
    ly = dy * c - dx * s
    ex = lx - min(max(lx, x0), x1)
    ey = ly - min(max(ly, -hy), hy)
    e2 = ex * ex + ey * ey
    reach = rr + g.rb
    if e2 >= (reach - _SLOP) ** 2:
        return 0.0, 0.0, 0.0, False
    depth = reach - math.sqrt(e2)
    if e2 < 1e-18:
        # A box centre inside the core (a deep sweep by a turning robot) leaves by the nearest
        # face.
        faces = (x1 - lx, lx - x0, hy - ly, ly + hy)
        best = 0
        for f in range(1, 4):
            if faces[f] < faces[best]:
                best = f
        ex = 1.0 if best == 0 else (-1.0 if best == 1 else 0.0)
        ey = 1.0 if best == 2 else (-1.0 if best == 3 else 0.0)
        depth = faces[best] + reach
        e2 = 1.0
    k = depth / math.sqrt(max(e2, 1e-18))
    kx = k * ex
    ky = k * ey
    front = lx > x1 and abs(ly) <= hy + reach
    return kx * c - ky * s, kx * s + ky * c, depth, front


@kernel
def _join_chain(
    yielded: int, by: int, rank: np.ndarray, pusher: np.ndarray, owner: np.ndarray,
    boxes: np.ndarray, pose: np.ndarray,
) -> None:  # fmt: skip
    # Box ``yielded`` gave way to box ``by``: it takes the chain's robot and rank.
    if pusher[by] < 0:
        return
    who = pusher[by]
    far = math.hypot(boxes[yielded, 0] - pose[who, 0], boxes[yielded, 1] - pose[who, 1])
    new = math.floor(rank[by]) + 1.0 + 0.1 * far
    if new < rank[yielded]:
        rank[yielded] = new
        pusher[yielded] = pusher[by]
        owner[yielded] = owner[by]


@kernel
def _box_box(
    g: Geometry, boxes: np.ndarray, pose: np.ndarray, check: np.ndarray, rank: np.ndarray,
    pusher: np.ndarray, owner: np.ndarray, held: np.ndarray, gave: np.ndarray,
    moved: np.ndarray, cell: np.ndarray, heads: np.ndarray, nexts: np.ndarray, cells: int,
) -> None:  # fmt: skip
    # Separate every overlapping pair that involves a box marked in ``check``; all shifts are
    # computed from the same positions, then applied. A grid of cells one box wide finds the
    # neighbours.
    nb = boxes.shape[0]
    size = g.box_size
    mx = np.zeros(nb)
    my = np.zeros(nb)
    pairs_i = []
    pairs_j = []
    weights_i = []
    weights_j = []
    for i in range(nb):
        if not check[i]:
            continue
        ci = cell[i]
        cx, cy = ci % cells, ci // cells
        for oy in range(-1, 2):
            for ox in range(-1, 2):
                nx, ny = cx + ox, cy + oy
                if nx < 0 or ny < 0 or nx >= cells or ny >= cells:
                    continue
                j = heads[ny * cells + nx]
                while j >= 0:
                    # A pair of two checked boxes is met twice; take it once.
                    if j != i and not (check[j] and j < i):
                        dx = boxes[i, 0] - boxes[j, 0]
                        dy = boxes[i, 1] - boxes[j, 1]
                        d2 = dx * dx + dy * dy
                        if d2 < (size - _SLOP) ** 2:
                            if d2 < 1e-18:
                                dx, dy, d2 = 1.0, 0.0, 1.0
                            d = math.sqrt(d2)
                            k = (size - d) / d
                            # Share of the overlap each box gives way by: a held box none; else
                            # the box of higher rank all of it; equal ranks half each. A box
                            # that gave way before in this step and must again is wedged: it
                            # shares the overlap, so the jam spreads back along the chain.
                            if rank[i] < rank[j]:
                                by_rank = 0.0
                            elif rank[i] > rank[j]:
                                by_rank = 1.0
                            else:
                                by_rank = 0.5
                            if (by_rank == 1.0 and gave[i]) or (by_rank == 0.0 and gave[j]):
                                by_rank = 0.5
                            if held[i] and held[j]:
                                wi, wj = 0.5, 0.5
                            elif held[i]:
                                wi, wj = 0.0, 1.0
                            elif held[j]:
                                wi, wj = 1.0, 0.0
                            else:
                                wi, wj = by_rank, 1.0 - by_rank
                            mx[i] += wi * k * dx
                            my[i] += wi * k * dy
                            mx[j] -= wj * k * dx
                            my[j] -= wj * k * dy
                            pairs_i.append(i)
                            pairs_j.append(j)
                            weights_i.append(wi)
                            weights_j.append(wj)
                    j = nexts[j]
    for i in range(nb):
        if mx[i] != 0.0 or my[i] != 0.0:
            boxes[i, 0] += mx[i]
            boxes[i, 1] += my[i]
    count = len(pairs_i)
    for p in range(count):
        i, j, wi, wj = pairs_i[p], pairs_j[p], weights_i[p], weights_j[p]
        if wi > 0.0:
            moved[i] = True
        if wj > 0.0:
            moved[j] = True
        if wi == 1.0:
            gave[i] = True
        if wj == 1.0:
            gave[j] = True
    # The box that gave way all of it joins its pusher's chain, one link farther.
    for p in range(count):
        if weights_i[p] == 1.0:
            _join_chain(pairs_i[p], pairs_j[p], rank, pusher, owner, boxes, pose)
    for p in range(count):
        if weights_j[p] == 1.0:
            _join_chain(pairs_j[p], pairs_i[p], rank, pusher, owner, boxes, pose)
    # A box that gave way to a held box is itself held now (decided on the held flags from
    # before this pass).
    newly = np.zeros(nb, dtype=np.bool_)
    for p in range(count):
        i, j = pairs_i[p], pairs_j[p]
        if held[j] and not held[i]:
            newly[i] = True
        elif held[i] and not held[j]:
            newly[j] = True
    for b in range(nb):
        if newly[b]:
            held[b] = True


@kernel
def _grid(
    boxes: np.ndarray, lo: float, cell_size: float, cells: int, cell: np.ndarray,
    heads: np.ndarray, nexts: np.ndarray,
) -> None:  # fmt: skip
    heads[:] = -1
    for i in range(boxes.shape[0]):
        gx = int((boxes[i, 0] - lo) / cell_size)
        gy = int((boxes[i, 1] - lo) / cell_size)
        gx = min(max(gx, 0), cells - 1)
        gy = min(max(gy, 0), cells - 1)
        c = gy * cells + gx
        cell[i] = c
        nexts[i] = heads[c]
        heads[c] = i


@kernel
def _relax(
    g: Geometry, pose: np.ndarray, boxes: np.ndarray, near: np.ndarray, active: np.ndarray,
    rank: np.ndarray, pusher: np.ndarray, owner: np.ndarray, held: np.ndarray,
    pushed: np.ndarray, gave: np.ndarray, backoffs: np.ndarray, robots_yield: bool,
) -> np.ndarray:  # fmt: skip
    # Passes of robots pushing boxes, boxes pushing boxes and walls holding boxes, until nothing
    # moves or the passes run out; returns the boxes moved by the last pass (those that may
    # still overlap). ``near`` (updated) marks the boxes that may touch a robot. With
    # ``robots_yield`` a robot backs off a box that cannot give way; without, robots stand like
    # walls and every box they touch leaves them and is held.
    n = pose.shape[0]
    nb = boxes.shape[0]
    lo_w, hi_w = g.rb - g.wall_half, g.wall_half - g.rb
    cells = max(1, int(2 * g.wall_half / g.box_size) + 1)
    cell = np.empty(nb, dtype=np.int64)
    heads = np.empty(cells * cells, dtype=np.int64)
    nexts = np.empty(nb, dtype=np.int64)
    c = np.empty(n)
    s = np.empty(n)
    px = np.empty(n)
    py = np.empty(n)
    depth = np.empty(n)
    blade = np.empty(n, dtype=np.bool_)
    back_x = np.zeros(n)
    back_y = np.zeros(n)
    back_d = np.zeros(n)
    # Headings do not change here (robots only back off), so their trigonometry holds for every
    # pass.
    for i in range(n):
        c[i] = math.cos(pose[i, 2])
        s[i] = math.sin(pose[i, 2])
    for _ in range(g.box_iterations):
        moved = np.zeros(nb, dtype=np.bool_)
        robots_moved = False
        back_d[:] = 0.0
        # Boxes move by the sum of the pushes of every robot touching them (computed from the
        # positions at the start of the pass).
        shift = np.zeros((nb, 2))
        for b in range(nb):
            if not near[b]:
                continue
            touched_any = False
            again = False
            deepest = 0.0
            who = -1
            blade_who = -1
            for r in range(n):
                px[r], py[r], depth[r], blade[r] = _robot_box(
                    g, boxes[b, 0], boxes[b, 1], pose[r, 0], pose[r, 1], c[r], s[r]
                )
                if depth[r] > 0.0:
                    touched_any = True
                    if robots_yield and pushed[b, r]:
                        again = True
            if not touched_any:
                continue
            if robots_yield:
                # A box pushed back into a robot that pushed it before in this step is wedged
                # between that robot and something else: the robot backs off instead.
                if again:
                    held[b] = True
                for r in range(n):
                    if depth[r] > 0.0:
                        pushed[b, r] = True
                free = not held[b]
            else:
                held[b] = True
                free = True
            if free:
                for r in range(n):
                    if depth[r] > 0.0:
                        shift[b, 0] += px[r]
                        shift[b, 1] += py[r]
                        if depth[r] > deepest:
                            deepest = depth[r]
                            who = r
                        if blade[r] and blade_who < 0:
                            blade_who = r
                moved[b] = True
            else:
                # A held box does not give way: each robot touching it backs off by its
                # deepest overlap with a held box, and its blade still feels the chain.
                for r in range(n):
                    if depth[r] > back_d[r]:
                        back_d[r] = depth[r]
                        back_x[r] = px[r]
                        back_y[r] = py[r]
                    if depth[r] > 0.0 and blade[r] and blade_who < 0:
                        blade_who = r
            if free and who >= 0:
                pusher[b] = who
            if blade_who >= 0:
                owner[b] = blade_who
        for b in range(nb):
            if moved[b]:
                boxes[b, 0] += shift[b, 0]
                boxes[b, 1] += shift[b, 1]
                if pusher[b] >= 0:
                    who = pusher[b]
                    far = math.hypot(boxes[b, 0] - pose[who, 0], boxes[b, 1] - pose[who, 1])
                    rank[b] = min(rank[b], 1.0 + 0.1 * far)
        worst = 0
        for r in range(n):
            worst = max(worst, backoffs[r])
        any_back = False
        for r in range(n):
            if back_d[r] > 0.0:
                any_back = True
                pose[r, 0] -= back_x[r]
                pose[r, 1] -= back_y[r]
                backoffs[r] += 1
        if any_back:
            # A robot that had to back off twice is wedged: it is left to the clean-up rather
            # than rocked to and fro.
            robots_moved = worst < 2
            _keep_inside_walls(g, pose)
        check = np.zeros(nb, dtype=np.bool_)
        any_check = False
        for b in range(nb):
            if active[b] or moved[b]:
                check[b] = True
                any_check = True
        if any_check:
            _grid(boxes, -g.wall_half, g.box_size, cells, cell, heads, nexts)
            _box_box(
                g, boxes, pose, check, rank, pusher, owner, held, gave, moved, cell, heads,
                nexts, cells,
            )  # fmt: skip
        # Walls hold boxes: a clamped box cannot give way any more this step.
        any_moved = False
        for b in range(nb):
            if moved[b]:
                any_moved = True
                x, y = boxes[b, 0], boxes[b, 1]
                cx = min(max(x, lo_w), hi_w)
                cy = min(max(y, lo_w), hi_w)
                if cx != x or cy != y:
                    boxes[b, 0] = cx
                    boxes[b, 1] = cy
                    held[b] = True
                near[b] = True
        active = moved
        if not (any_moved or robots_moved):
            break
    return active


@kernel
def _push_boxes(
    g: Geometry, pose: np.ndarray, start: np.ndarray, boxes: np.ndarray, pending: np.ndarray,
    force: np.ndarray, need_force: bool,
) -> None:  # fmt: skip
    n = pose.shape[0]
    nb = boxes.shape[0]
    near = np.zeros(nb, dtype=np.bool_)
    for b in range(nb):
        if pending[b]:
            near[b] = True
            continue
        for r in range(n):
            dx = boxes[b, 0] - pose[r, 0]
            dy = boxes[b, 1] - pose[r, 1]
            if dx * dx + dy * dy < g.box_reach2:
                near[b] = True
                break
    rank = np.full(nb, np.inf)
    pusher = np.full(nb, -1, dtype=np.int64)
    owner = np.full(nb, -1, dtype=np.int64)
    held = np.zeros(nb, dtype=np.bool_)
    pushed = np.zeros((nb, n), dtype=np.bool_)
    gave = np.zeros(nb, dtype=np.bool_)
    backoffs = np.zeros(n, dtype=np.int64)
    active = _relax(
        g, pose, boxes, near, pending.copy(), rank, pusher, owner, held, pushed, gave, backoffs,
        True,
    )  # fmt: skip
    # A robot still in a box is wedged between boxes that cannot give way: it stays where it
    # was before this step, and the boxes settle around the robots, which no longer move.
    # Should a box held by a wall still be inside a robot, the robot backs off it, and the boxes
    # settle again.
    stuck = np.zeros(n, dtype=np.bool_)
    c = np.empty(n)
    s = np.empty(n)
    for round_ in range(_SETTLE_ROUNDS):
        any_stuck = False
        deep = np.zeros(n)
        dpx = np.zeros(n)
        dpy = np.zeros(n)
        # Per round: the first round puts stuck robots back where they were, heading included.
        for r in range(n):
            c[r] = math.cos(pose[r, 2])
            s[r] = math.sin(pose[r, 2])
        for b in range(nb):
            if not near[b]:
                continue
            for r in range(n):
                px, py, depth, _ = _robot_box(
                    g, boxes[b, 0], boxes[b, 1], pose[r, 0], pose[r, 1], c[r], s[r]
                )
                if depth > deep[r]:
                    deep[r] = depth
                    dpx[r] = px
                    dpy[r] = py
                    any_stuck = True
        if not any_stuck:
            break
        for r in range(n):
            stuck[r] = deep[r] > 0.0
            if not stuck[r]:
                continue
            if round_ == 0:
                pose[r, 0] = start[r, 0]
                pose[r, 1] = start[r, 1]
                pose[r, 2] = start[r, 2]
            else:
                pose[r, 0] -= dpx[r]
                pose[r, 1] -= dpy[r]
        if round_ > 0:
            _keep_inside_walls(g, pose)
        rank2 = np.full(nb, np.inf)
        pusher2 = np.full(nb, -1, dtype=np.int64)
        owner2 = np.full(nb, -1, dtype=np.int64)
        held2 = np.zeros(nb, dtype=np.bool_)
        pushed2 = np.zeros((nb, n), dtype=np.bool_)
        gave2 = np.zeros(nb, dtype=np.bool_)
        backoffs2 = np.zeros(n, dtype=np.int64)
        active = _relax(
            g, pose, boxes, near, active, rank2, pusher2, owner2, held2, pushed2, gave2,
            backoffs2, False,
        )  # fmt: skip
    pending[:] = active
    if need_force:
        counts = np.zeros(n)
        for b in range(nb):
            if owner[b] >= 0:
                counts[owner[b]] += 1.0
        for r in range(n):
            # The strongest push of this step's contact rounds.
            value = min(counts[r] * g.force_per_box, 1.0)
            if value > force[r]:
                force[r] = value


@kernel
def clamp_commands(commands: np.ndarray, cmd: np.ndarray) -> None:
    """``cmd`` = ``commands`` clamped to [-1, 1], NaN as 0 (a robot's wheels take no more)."""
    for i in range(cmd.shape[0]):
        for k in range(2):
            v = commands[i, k]
            cmd[i, k] = 0.0 if v != v else min(max(v, -1.0), 1.0)


@kernel
def step_world(
    g: Geometry, pose: np.ndarray, cmd: np.ndarray, force: np.ndarray, boxes: np.ndarray,
    pending: np.ndarray, need_force: bool,
) -> None:  # fmt: skip
    """Advance one arena by one step of ``g.dt`` with the commands ``cmd``."""
    start = pose.copy()
    _move(g, pose, cmd)
    force[:] = 0.0
    for round_ in range(_CONTACT_ROUNDS):
        # Robots part first, then boxes give way to them; a robot the boxes moved (backed off
        # or sent back) may touch another robot again, hence another round.
        parted = _separate_robots(g, pose)
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


# --------------------------------------------------------------------------- sensors


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
    sn: Sensing, bodies: np.ndarray, me: int, sx: float, sy: float, cp: float, sp: float,
    step: int, channel: int,
) -> float:  # fmt: skip
    # ``bodies`` (N, 2): the centre of every robot's body circle.
    n = bodies.shape[0]
    r = sn.robot_radius
    best = np.inf
    if sn.ir_model == IR_CONE:
        ca, sa = sn.ir_ca, sn.ir_sa
        reach2 = (sn.ir_range + r) ** 2
        for j in range(n):
            if j == me:
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
        if j == me:
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


@kernel
def sense(
    sn: Sensing, pose: np.ndarray, force: np.ndarray, step: int, out: np.ndarray,
    full: np.ndarray,
) -> None:  # fmt: skip
    """Every robot's sensor values for the arena as it is at ``step`` into ``out`` (N, R), in
    the order of ``sn.columns``; ``full`` (N, 12) is scratch space."""
    n = pose.shape[0]
    bodies = np.empty((n, 2))
    for i in range(n):
        bodies[i, 0] = pose[i, 0] + sn.body_offset * math.cos(pose[i, 2])
        bodies[i, 1] = pose[i, 1] + sn.body_offset * math.sin(pose[i, 2])
    for i in range(n):
        x, y, th = pose[i, 0], pose[i, 1], pose[i, 2]
        c, s = math.cos(th), math.sin(th)
        if sn.need_ir:
            for k in range(7):
                px, py = IR_POSITIONS[k, 0], IR_POSITIONS[k, 1]
                sx = x + c * px - s * py
                sy = y + s * px + c * py
                # cos and sin of th + heading, from those of th and of the heading
                cp = c * _IR_COS[k] - s * _IR_SIN[k]
                sp = s * _IR_COS[k] + c * _IR_SIN[k]
                full[i, _IR0 + k] = _ir_value(sn, bodies, i, sx, sy, cp, sp, step, k)
        if sn.need_ground:
            half = sn.arena_half
            for k in range(2):
                px, py = GROUND_POSITIONS[k, 0], GROUND_POSITIONS[k, 1]
                gx = x + c * px - s * py
                gy = y + s * px + c * py
                on = abs(gx) <= half and abs(gy) <= half
                value = sn.ground_carpet if on else sn.ground_outside
                if value > 0.0 and sn.ground_noise > 0.0:
                    value += sn.ground_noise * value * gaussian(sn.seed, step, i, 48 + k)
                full[i, _GROUND0 + k] = value
        if sn.need_force:
            full[i, _FORCE] = force[i]
        if sn.need_light:
            for k in range(2):
                if sn.light:
                    px, py = sn.light_offsets[k, 0], sn.light_offsets[k, 1]
                    lx = x + c * px - s * py
                    ly = y + s * px + c * py
                    h2 = sn.lamp_h2
                    ratio = h2 / (h2 + lx * lx + ly * ly)
                    full[i, _LIGHT0 + k] = sn.light_centre * ratio**sn.light_exponent
                else:
                    full[i, _LIGHT0 + k] = sn.light_uniform
        for j in range(sn.columns.shape[0]):
            value = full[i, sn.columns[j]]
            if sn.noise > 0.0:
                value += sn.noise * gaussian(sn.seed, step, i, j)
            out[i, j] = min(max(value, 0.0), 1.0)
