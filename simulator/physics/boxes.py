"""Contacts with boxes: robots push boxes and boxes push boxes.

The box farther down a pushing chain gives way. A box held by a wall, or wedged between a robot
and other boxes, cannot give way: the robot pushing it backs off instead. A robot still wedged
among boxes stays where it was before the step and the boxes settle around it. The force
sensor counts the boxes a robot's blade moved, directly or through a chain.
"""

from __future__ import annotations

import math

import numpy as np

from minimize_surprise.jit import kernel
from simulator.physics.contacts import _SLOP, _keep_inside_walls
from simulator.physics.model import Geometry

# Rounds of settling boxes around robots wedged among them.
_SETTLE_ROUNDS = 3


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
    pairs: np.ndarray, shares: np.ndarray,
) -> None:  # fmt: skip
    # Separate every overlapping pair that involves a box marked in ``check``; all shifts are
    # computed from the same positions, then applied. A grid of cells one box wide finds the
    # neighbours. ``pairs`` and ``shares`` (P, 2): scratch for the pairs found and each box's
    # share of their overlap (grown here should a jam hold more than P pairs).
    nb = boxes.shape[0]
    size = g.box_size
    mx = np.zeros(nb)
    my = np.zeros(nb)
    count = 0
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
                            if count == pairs.shape[0]:
                                pairs, shares = _grown(pairs, shares)
                            pairs[count, 0] = i
                            pairs[count, 1] = j
                            shares[count, 0] = wi
                            shares[count, 1] = wj
                            count += 1
                    j = nexts[j]
    for i in range(nb):
        if mx[i] != 0.0 or my[i] != 0.0:
            boxes[i, 0] += mx[i]
            boxes[i, 1] += my[i]
    for p in range(count):
        i, j, wi, wj = pairs[p, 0], pairs[p, 1], shares[p, 0], shares[p, 1]
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
        if shares[p, 0] == 1.0:
            _join_chain(pairs[p, 0], pairs[p, 1], rank, pusher, owner, boxes, pose)
    for p in range(count):
        if shares[p, 1] == 1.0:
            _join_chain(pairs[p, 1], pairs[p, 0], rank, pusher, owner, boxes, pose)
    # A box that gave way to a held box is itself held now (decided on the held flags from
    # before this pass).
    newly = np.zeros(nb, dtype=np.bool_)
    for p in range(count):
        i, j = pairs[p, 0], pairs[p, 1]
        if held[j] and not held[i]:
            newly[i] = True
        elif held[i] and not held[j]:
            newly[j] = True
    for b in range(nb):
        if newly[b]:
            held[b] = True


@kernel
def _grown(pairs: np.ndarray, shares: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # The pair scratch of _box_box twice as long, the pairs so far kept.
    more_pairs = np.empty((2 * pairs.shape[0], 2), dtype=np.int64)
    more_shares = np.empty((2 * pairs.shape[0], 2))
    for k in range(pairs.shape[0]):  # element by element: no slice's shape checks to compile
        more_pairs[k, 0], more_pairs[k, 1] = pairs[k, 0], pairs[k, 1]
        more_shares[k, 0], more_shares[k, 1] = shares[k, 0], shares[k, 1]
    return more_pairs, more_shares


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
    lo_x, hi_x = g.rb - g.wall_hx, g.wall_hx - g.rb
    lo_y, hi_y = g.rb - g.wall_hy, g.wall_hy - g.rb
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
    # Per pass: the boxes it moves (two buffers, taking turns: the last pass's stay ``active``),
    # how far, and which to check against the others; allocated once.
    moved_buffers = np.zeros((2, nb), dtype=np.bool_)
    shift = np.empty((nb, 2))
    check = np.empty(nb, dtype=np.bool_)
    pairs = np.empty((max(16, nb), 2), dtype=np.int64)
    shares = np.empty((max(16, nb), 2))
    for pass_ in range(g.box_iterations):
        moved = moved_buffers[pass_ % 2]
        moved[:] = False
        robots_moved = False
        back_d[:] = 0.0
        # Boxes move by the sum of the pushes of every robot touching them (computed from the
        # positions at the start of the pass).
        for b in range(nb):
            if not near[b]:
                continue
            shift[b, 0] = 0.0
            shift[b, 1] = 0.0
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
        any_check = False
        for b in range(nb):
            check[b] = active[b] or moved[b]
            any_check |= check[b]
        if any_check:
            _grid(boxes, -g.wall_half, g.box_size, cells, cell, heads, nexts)
            _box_box(
                g, boxes, pose, check, rank, pusher, owner, held, gave, moved, cell, heads,
                nexts, cells, pairs, shares,
            )  # fmt: skip
        # Walls hold boxes: a clamped box cannot give way any more this step.
        any_moved = False
        for b in range(nb):
            if moved[b]:
                any_moved = True
                x, y = boxes[b, 0], boxes[b, 1]
                cx = min(max(x, lo_x), hi_x)
                cy = min(max(y, lo_y), hi_y)
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
