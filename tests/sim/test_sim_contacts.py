"""Boxes, the blade and the force sensor; nothing overlaps (simulator.world)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from simulator.scenarios import scenario_config
from simulator.world import World

FORCE = 9  # index of "force" in the boxes scenario's sensors


def pusher(x=-0.3, boxes=(), **overrides) -> World:
    world = World(scenario_config("boxes", {"robots": 1, **overrides}), seed=0)
    world.set_pose(0, x, 0.0, 0.0)
    world.set_box_positions(np.array(boxes, dtype=float).reshape(-1, 2))
    return world


def row_ahead(world: World, count: int, gap: float = 0.002) -> np.ndarray:
    # ``count`` boxes in a row ahead of robot 0's blade, ``gap`` apart.
    x = world.poses[0, 0] + world.config.blade_x + world.config.blade_thickness / 2
    size = world.config.box_size
    return np.array([[x + gap + size / 2 + k * (size + gap), 0.0] for k in range(count)])


def overlaps(world: World) -> dict[str, float]:
    """Deepest overlap of each kind, in metres (0 when apart); computed independently of the
    world's own contact code."""
    cfg = world.config
    x, y, th = world.poses.T
    c, s = np.cos(th), np.sin(th)
    cx, cy = x + cfg.body_offset * c, y + cfg.body_offset * s
    r, wall, n = cfg.robot_radius, cfg.wall_half, len(x)
    out = {}
    gaps = np.hypot(cx[:, None] - cx, cy[:, None] - cy) + 9 * np.eye(n)
    out["robot-robot"] = max(0.0, float((2 * r - gaps).max()))
    out["robot-wall"] = max(0.0, float((np.abs(np.r_[cx, cy]) + r - wall).max()))
    boxes = world.box_positions
    if len(boxes):
        rb = cfg.box_size / 2
        out["box-wall"] = max(0.0, float((np.abs(boxes) + rb - wall).max()))
        apart = np.hypot(*(boxes[:, None] - boxes[None]).transpose(2, 0, 1)) + 9 * np.eye(
            len(boxes)
        )
        out["box-box"] = max(0.0, float((cfg.box_size - apart).max()))
        if cfg.has_blade:
            # Boxes meet the outline from the flat rear (3 cm behind the wheels) to the blade.
            dx, dy = boxes[:, 0, None] - x, boxes[:, 1, None] - y
            lx, ly = dx * c + dy * s, dy * c - dx * s
            rr = cfg.blade_thickness / 2
            hy = cfg.blade_width / 2 - rr
            ex = lx - np.clip(lx, rr - 0.03, cfg.blade_x)
            ey = ly - np.clip(ly, -hy, hy)
            depth = rr + rb - np.hypot(ex, ey)
        else:
            depth = r + rb - np.hypot(boxes[:, 0, None] - cx, boxes[:, 1, None] - cy)
        out["box-robot"] = max(0.0, float(depth.max()))
    return out


def test_pushing_boxes_raises_the_force_and_moves_them():
    world = pusher()
    world.set_box_positions(row_ahead(world, 5))
    start = world.box_positions.copy()
    assert world.sensor_values(0)[FORCE] == 0.0
    world.set_command(0, 1.0, 1.0)
    forces = []
    for _ in range(20):
        world.step()
        forces.append(world.sensor_values(0)[FORCE])
    # Once the blade meets the row, it pushes all five: 5 x 0.025.
    assert forces[-1] == pytest.approx(0.125)
    moved = world.box_positions - start
    assert (moved[:, 0] > 0.1).all()
    assert np.abs(moved[:, 1]).max() < 1e-9  # straight ahead, the row stays a row
    # Standing still or backing off, the blade feels nothing.
    world.set_command(0, 0.0, 0.0)
    world.step()
    assert world.sensor_values(0)[FORCE] == 0.0
    world.set_command(0, -1.0, -1.0)
    world.step()
    assert world.sensor_values(0)[FORCE] == 0.0


def test_ten_boxes_push_about_a_quarter():
    world = pusher(x=-0.5)
    world.set_box_positions(row_ahead(world, 10))
    world.set_command(0, 1.0, 1.0)
    for _ in range(15):
        world.step()
    assert world.sensor_values(0)[FORCE] == pytest.approx(0.25)


def test_the_force_saturates_at_one():
    world = pusher(x=-0.5, force_per_box=0.2)
    world.set_box_positions(row_ahead(world, 8))
    world.set_command(0, 1.0, 1.0)
    for _ in range(15):
        world.step()
    assert world.sensor_values(0)[FORCE] == 1.0


def test_boxes_stop_at_the_wall_and_so_does_the_robot_behind_them():
    world = pusher(x=0.3)
    world.set_box_positions(row_ahead(world, 3))
    world.set_command(0, 1.0, 1.0)
    for _ in range(60):
        world.step()
        assert max(overlaps(world).values()) < 2e-5
    boxes = world.box_positions
    wall, rb = world.config.wall_half, world.config.box_size / 2
    assert boxes[:, 0].max() == pytest.approx(wall - rb)
    # Jammed against the wall, the robot still pushes all three.
    assert world.sensor_values(0)[FORCE] == pytest.approx(0.075)
    before = world.poses.copy()
    world.step()
    np.testing.assert_allclose(world.poses, before, atol=1e-4)


def test_the_ir_does_not_see_boxes():
    world = pusher()
    world.set_box_positions(row_ahead(world, 1, gap=0.01))
    assert world.sensor_values(0)[:7].tolist() == [0.0] * 7


def test_a_robot_without_a_blade_pushes_boxes_with_its_body():
    world = World(scenario_config("basic", {"robots": 1, "boxes": True}), seed=0)
    world.set_pose(0, -0.3, 0.0, 0.0)
    front = -0.3 + world.config.body_offset + world.config.robot_radius
    world.set_box_positions(np.array([[front + 0.02, 0.0]]))
    world.set_command(0, 1.0, 1.0)
    for _ in range(10):
        world.step()
        assert max(overlaps(world).values()) < 2e-5
    assert world.box_positions[0, 0] > front + 0.1
    assert world.forces.tolist() == [0.0]


def test_a_turning_blade_sweeps_boxes_aside():
    world = pusher()
    x, y = world.poses[0, :2]
    # A box just off the blade's left end.
    world.set_box_positions(np.array([[x + 0.06, y + 0.085]]))
    world.set_command(0, -1.0, 1.0)
    for _ in range(12):
        world.step()
        assert max(overlaps(world).values()) < 2e-5
    assert np.hypot(*(world.box_positions[0] - (x + 0.06, y + 0.085))) > 0.01


# Deepest overlaps allowed after any step, in metres. Overlaps shallower than 10 um are left
# alone by design; robots pressed together against a wall or boxes settle within a millimetre.
PAPER_TOLERANCE = {
    "robot-robot": 1e-3,
    "robot-wall": 1e-12,
    "box-wall": 1e-12,
    "box-robot": 2e-5,
    "box-box": 1e-3,
}
# Ten robots with blades among boxes on 1.0 m jam far more than the paper's arenas: a box
# squeezed between two robots may stay a few millimetres deep for a step or two.
CROWDED_TOLERANCE = {
    "robot-robot": 5e-3,
    "robot-wall": 1e-12,
    "box-wall": 1e-12,
    "box-robot": 5e-3,
    "box-box": 5e-3,
}

unit = st.floats(-1.0, 1.0, allow_nan=False)


@settings(
    max_examples=12,
    deadline=None,
    derandomize=True,
    # Shrinking a long run of commands takes minutes; a failure is reported as found.
    phases=[Phase.explicit, Phase.generate],
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    scenario=st.sampled_from(["basic", "boxes", "gradient", "crowded"]),
    seed=st.integers(0, 2**16),
    segments=st.lists(st.lists(st.tuples(unit, unit), min_size=10, max_size=10), min_size=4),
)
def test_nothing_overlaps_after_many_random_steps(scenario, seed, segments):
    if scenario == "crowded":
        cfg = scenario_config("boxes", {"robots": 10, "start": "random", "arena_side": 1.0})
        tolerance = CROWDED_TOLERANCE
    else:
        cfg = scenario_config(scenario)
        tolerance = PAPER_TOLERANCE
    world = World(cfg, seed=seed)
    count = len(world.box_positions)
    for segment in segments[:15]:
        world.set_commands(np.array(segment[: cfg.robots]))
        for _ in range(10):
            world.step()
            for kind, depth in overlaps(world).items():
                assert depth <= tolerance[kind], (kind, depth, world.steps)
    # Given a few quiet steps, the jams clear.
    world.set_commands(np.zeros((cfg.robots, 2)))
    for _ in range(5):
        world.step()
    assert max(overlaps(world).values()) <= 2e-4
    assert len(world.box_positions) == count
    assert np.isfinite(world.poses).all() and np.isfinite(world.sensor_matrix()).all()
    values = world.sensor_matrix()
    assert values.min() >= 0.0 and values.max() <= 1.0
    assert math.isclose(world.time, world.steps * cfg.dt)


def test_a_jam_of_more_pairs_than_the_scratch_holds_parts_the_same():
    # Boxes part pair by pair into scratch arrays that grow in a jam larger than they are; the
    # result must not depend on where they started.
    from simulator.physics.boxes import _box_box, _grid

    world = World(scenario_config("boxes", {"robots": 1}), seed=3)
    geometry, _ = world.kernel_constants
    rng = np.random.default_rng(3)
    nb = 40
    start = rng.normal(0.0, 0.01, (nb, 2))  # forty boxes piled within a few centimetres
    cells = max(1, int(2 * geometry.wall_half / geometry.box_size) + 1)
    results = []
    for capacity in (1, 4096):
        boxes = start.copy()
        flags = [np.zeros(nb, dtype=np.bool_) for _ in range(3)]
        rank, pusher, owner = np.full(nb, np.inf), np.full(nb, -1), np.full(nb, -1)
        cell, heads, nexts = (
            np.empty(nb, np.int64),
            np.empty(cells * cells, np.int64),
            np.empty(nb, np.int64),
        )
        _grid(boxes, -geometry.wall_half, geometry.box_size, cells, cell, heads, nexts)
        _box_box(
            geometry, boxes, np.zeros((1, 3)), np.ones(nb, dtype=np.bool_), rank, pusher, owner,
            *flags, cell, heads, nexts, cells, np.empty((capacity, 2), np.int64),
            np.empty((capacity, 2)),
        )  # fmt: skip
        results.append((boxes, *flags))
    assert not np.array_equal(results[0][0], start)  # they did part
    for small, large in zip(results[0], results[1], strict=True):
        assert np.array_equal(small, large)
