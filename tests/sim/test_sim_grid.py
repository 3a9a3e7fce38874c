"""The neighbour grid of large swarms gives what looking at every pair gives, bit for bit
(simulator.physics.grid).

The grid only narrows down which other robots a robot's contacts and IR sensors look at, and
visits them in increasing index as the all-pairs loops do (every push is added in the same
order; the IR takes a minimum), so the poses, boxes, forces and sensor values of a swarm stepped
with it are identical to those stepped without it, not merely close: the tests compare with
``array_equal``. Each swarm is crowded (two to three times the basic arena's density), its
robots driving random commands into each other, into the walls and, with blades, into boxes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from simulator import physics
from simulator.experiment import world_overrides
from simulator.physics.contacts import contact_reach
from simulator.physics.grid import build, gather, grid_side, new_cells
from simulator.scenarios import WorldConfig, scenario_config
from simulator.world import World

NEVER = 1 << 40  # grid_robots: look at every pair whatever the number of robots


def world(setting: str, scenario: str, **overrides: object) -> WorldConfig:
    return scenario_config(scenario, {**world_overrides(setting, scenario), **overrides})


def step_swarm(config: WorldConfig, steps: int, *, grid: bool, seed: int = 3) -> dict:
    """Step a fresh world of ``config`` with random commands held 10 steps (mostly forward, so
    that robots drive into each other), every robot's sensors read before every step, with the
    grid or with every pair; everything every step."""
    world = World(config, seed=seed)
    g, sn = world.kernel_constants
    n = world.n_robots
    if grid:
        # The grid is on for this many robots, and has more than one cell for both ranges.
        assert n >= physics.GRID_ROBOTS == g.grid_robots == sn.grid_robots
        assert grid_side(g.wall_half, contact_reach(g), n) > 1
        assert grid_side(sn.wall_half, sn.ir_reach, n) > 1
    else:
        g, sn = g._replace(grid_robots=NEVER), sn._replace(grid_robots=NEVER)
    pose, cmd, force, boxes, pending = (a.copy() for a in world.kernel_state)
    rng = np.random.default_rng(seed)
    commands = rng.uniform(-0.5, 1.0, size=(steps // 10 + 1, n, 2))
    values = np.empty((n, len(config.sensors)))
    work = physics.sense_work(n)
    out: dict[str, list[np.ndarray]] = {"pose": [], "values": [], "boxes": [], "force": []}
    for t in range(steps):
        physics.sense(sn, pose, force, t, values, work, True)
        physics.clamp_commands(commands[t // 10], cmd)
        physics.step_world(g, pose, cmd, force, boxes, pending, 0, len(boxes), sn.need_force, True)
        for key, array in (("pose", pose), ("values", values), ("boxes", boxes), ("force", force)):
            out[key].append(array.copy())
    return {key: np.stack(arrays) for key, arrays in out.items()}


def touching_steps(config: WorldConfig, poses: np.ndarray) -> int:
    """Steps after which some body touches another body or blade (within 1 mm of it)."""
    x, y, th = poses[:, :, 0], poses[:, :, 1], poses[:, :, 2]
    c, s = np.cos(th), np.sin(th)
    cx, cy = x + config.body_offset * c, y + config.body_offset * s
    eye = 9 * np.eye(poses.shape[1])
    gap = np.hypot(cx[:, :, None] - cx[:, None], cy[:, :, None] - cy[:, None]) + eye
    touch = gap.min(axis=(1, 2)) < 2 * config.robot_radius + 1e-3
    if config.has_blade:
        # From robot i's blade (a segment across its front) to robot j's body centre.
        hw = config.blade_width / 2
        ax, ay = x + config.blade_x * c - hw * s, y + config.blade_x * s + hw * c
        ux, uy = 2 * hw * s, -2 * hw * c
        wx, wy = cx[:, None, :] - ax[:, :, None], cy[:, None, :] - ay[:, :, None]
        t = np.clip((wx * ux[:, :, None] + wy * uy[:, :, None]) / (2 * hw) ** 2, 0.0, 1.0)
        blade = np.hypot(wx - t * ux[:, :, None], wy - t * uy[:, :, None]) + eye
        reach = config.robot_radius + config.blade_thickness / 2 + 1e-3
        touch |= blade.min(axis=(1, 2)) < reach
    return int(touch.sum())


def assert_same(config: WorldConfig, steps: int) -> dict:
    every_pair = step_swarm(config, steps, grid=False)
    with_grid = step_swarm(config, steps, grid=True)
    for key in every_pair:
        assert np.array_equal(with_grid[key], every_pair[key]), key
    assert np.isfinite(every_pair["pose"]).all()
    # The swarm was crowded: bodies touched in most steps, robots were pushed off the walls.
    assert touching_steps(config, every_pair["pose"]) > steps // 2
    wall = config.wall_half - config.robot_radius - abs(config.body_offset) - 1e-3
    assert (np.abs(every_pair["pose"][:, :, :2]) > wall).any()
    return every_pair


@pytest.mark.parametrize("setting", ["lab", "paper"])
def test_a_crowded_basic_swarm_is_the_same_with_the_grid(setting):
    # 120 robots at about 2.5 times the basic arena's density, the walls close and seen by the
    # IR: the lab's cone model, the paper's ray model with its noise.
    config = world(
        setting, "basic", robots=120, arena_side=2.2, wall_margin=0.05, walls_visible_to_ir=True,
        start_clearance=0.02, noise=0.01,
    )  # fmt: skip
    run = assert_same(config, 300)
    assert (run["values"][:, :, :7] > 0.05).mean() > 0.02  # the IR saw robots and walls


def test_a_crowded_swarm_of_bladed_robots_among_boxes_is_the_same_with_the_grid():
    # The boxes arena (the lab's: 10 cm steps, boxes at random) grown to 40 robots, 4.5 times
    # as many per area, started at random among 573 boxes: blades push bodies and boxes, boxes
    # push back, robots are wedged and sent back.
    config = world("lab", "boxes", robots=40, arena_side=1.6, start="random")
    run = assert_same(config, 300)
    moved = np.hypot(*(run["boxes"][-1] - run["boxes"][0]).T) > 1e-3
    assert moved.sum() > 20  # the robots pushed boxes
    assert (run["force"] > 0).any()


def test_a_robot_pushed_into_a_cell_beside_a_still_one_pushes_it_in_the_next_pass():
    # Contacts' later passes look only near the robots the last pass touched. Here robot A is
    # pushed by B across a cell border, into robot C two cells from A's old cell: C was
    # touched by nothing, and only the cells around A's new place say that C is to be looked
    # at in the second pass. Five columns of cells just wider than two body radii, the three
    # robots on the middle row, a fourth far away (the grid is on from four robots here).
    arena = World(world("paper", "basic", robots=4), seed=1)
    g = arena.kernel_constants[0]
    _, cmd, force, boxes, pending = arena.kernel_state
    r2 = contact_reach(g)
    g = g._replace(wall_half=2.5 * (r2 + 2e-6), grid_robots=4)
    assert grid_side(g.wall_half, r2, 4) == 5
    border = -g.wall_half + 2 * 2 * g.wall_half / 5  # between the second and third columns
    a = border - 1e-4
    centres = [(a - r2 + 2e-3, 0.0), (a, 0.0), (border + r2 + 5e-4, 0.0), (-a, 2 * r2)]
    # Headings 0: a body centre is body_offset ahead of the wheel axis.
    pose = np.array([(x - g.body_offset, y, 0.0) for x, y in centres])
    stepped = {}
    for grid, limit in ((True, 4), (False, NEVER)):
        p = pose.copy()
        cmd[:] = 0.0
        physics.step_world(
            g._replace(grid_robots=limit), p, cmd, force, boxes, pending, 0, len(boxes), False, True
        )
        stepped[grid] = p
    assert np.array_equal(stepped[True], stepped[False])
    # B and A parted in the first pass, A and C in the second: C moved, the far robot did not.
    assert stepped[False][2, 0] > pose[2, 0] + 1e-4
    assert np.array_equal(stepped[False][3], pose[3])


def test_the_grid_finds_every_point_in_range_in_increasing_index():
    rng = np.random.default_rng(5)
    half, reach = 1.0, 0.15
    points = rng.uniform(-1.05, 1.05, size=(400, 2))  # some beyond the walls
    points[7] = np.nan  # a NaN pose sits in a cell and meets nobody
    side = grid_side(half, reach, len(points))
    assert side == int(2 * half / (reach + 1e-6))
    cells = new_cells(len(points), side)
    build(points[:, 0].copy(), points[:, 1].copy(), half, *cells)
    assert sorted(cells.order) == list(range(len(points))) and cells.start[-1] == len(points)
    near = np.empty(len(points), dtype=np.int64)
    d = np.hypot(*(points[:, None] - points[None]).transpose(2, 0, 1))
    for i in range(len(points)):
        found = near[: gather(i, *cells, near, True)].copy()
        assert (np.diff(found) > 0).all() and i in found
        within = set(np.flatnonzero(d[i] < reach))
        assert within <= set(found)
        # Unordered (the IR's use: a nearest body is the same in any order), the same points.
        unsorted = near[: gather(i, *cells, near, False)]
        assert sorted(unsorted) == list(found)
    # Few robots in a large arena: no more cells than about 4 per robot.
    assert grid_side(100.0, reach, 50) == 2 * int(math.sqrt(50)) + 1
