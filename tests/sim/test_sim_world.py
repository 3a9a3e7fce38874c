"""The kinematic world: motion, contacts, sensors, determinism (simulator.world)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from minimize_surprise.sensors import ALL_SENSORS
from simulator.physics.model import gaussian, normal_quantile
from simulator.physics.motion import _wrap
from simulator.scenarios import scenario_config
from simulator.world import World

IR_F2 = 2
_WRAP_EDGES = [
    0.0, -0.0, math.pi, -math.pi, 2 * math.pi, -2 * math.pi, 3 * math.pi, -3 * math.pi,
    math.nextafter(math.pi, 0.0), math.nextafter(-math.pi, 0.0), math.nextafter(3 * math.pi, 0.0),
]  # fmt: skip


def lone_robot(x=0.0, y=0.0, theta=0.0, **overrides) -> World:
    world = World(scenario_config("basic", {"robots": 1, **overrides}), seed=0)
    world.set_pose(0, x, y, theta)
    return world


def body_centre(world: World, i: int) -> np.ndarray:
    x, y, th = world.poses[i]
    off = world.config.body_offset
    return np.array([x + off * math.cos(th), y + off * math.sin(th)])


# --- motion ----------------------------------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(st.floats(-30.0, 30.0) | st.sampled_from(_WRAP_EDGES))
def test_headings_wrap_as_pythons_modulo_to_the_bit(theta):
    # The compiled wrap skips fmod for angles near the range; it must give Python's modulo.
    expected = (theta + math.pi) % (2 * math.pi) - math.pi
    got = _wrap(theta)
    assert got == expected and math.copysign(1.0, got) == math.copysign(1.0, expected)


def test_full_speed_straight_covers_max_speed_times_time():
    world = lone_robot()
    world.set_command(0, 1.0, 1.0)
    for _ in range(10):
        world.step()
    x, y, th = world.poses[0]
    assert x == pytest.approx(0.106, abs=1e-12)  # the real robots' 10.6 cm/s
    assert y == 0.0 and th == 0.0
    assert world.time == pytest.approx(1.0) and world.steps == 10


def test_half_speed_is_half_as_far_and_backwards_goes_back():
    world = lone_robot()
    world.set_command(0, 0.5, 0.5)
    for _ in range(10):
        world.step()
    assert world.poses[0, 0] == pytest.approx(0.053, abs=1e-12)
    world.set_command(0, -1.0, -1.0)
    for _ in range(5):
        world.step()
    assert world.poses[0, 0] == pytest.approx(0.0, abs=1e-12)


def test_turning_on_the_spot_keeps_the_position():
    world = lone_robot(0.1, -0.2, 0.3)
    world.set_command(0, -1.0, 1.0)
    rate = 2 * 0.106 / 0.094  # rad/s with the Thymio's 9.4 cm wheel base
    for k in range(1, 60):
        world.step()
        x, y, th = world.poses[0]
        assert (x, y) == (0.1, -0.2)
        expected = (0.3 + rate * 0.1 * k + math.pi) % (2 * math.pi) - math.pi
        assert th == pytest.approx(expected, abs=1e-9)


def test_an_arc_follows_the_exact_circle():
    world = lone_robot()
    world.set_command(0, 0.5, 1.0)
    v, w = 0.75 * 0.106, 0.5 * 0.106 / 0.094
    for _ in range(20):
        world.step()
    t = 2.0
    x, y, th = world.poses[0]
    assert x == pytest.approx(v / w * math.sin(w * t), abs=1e-12)
    assert y == pytest.approx(v / w * (1 - math.cos(w * t)), abs=1e-12)
    assert th == pytest.approx(w * t, abs=1e-12)


def test_commands_are_clamped_and_nan_is_zero():
    world = lone_robot()
    world.set_command(0, 7.0, float("nan"))
    assert world.commands[0].tolist() == [1.0, 0.0]
    world.set_commands(np.array([[-3.0, np.nan]]))
    assert world.commands[0].tolist() == [-1.0, 0.0]


def test_state_views_are_read_only():
    world = lone_robot()
    with pytest.raises(ValueError):
        world.poses[0, 0] = 1.0
    with pytest.raises(ValueError):
        world.sensor_matrix()[0, 0] = 1.0


# --- walls and IR ----------------------------------------------------------------------------


def test_driving_at_a_visible_wall_raises_the_middle_sensor_and_never_passes():
    world = lone_robot(0.2, 0.0, 0.0, walls_visible_to_ir=True)
    wall = world.config.wall_half
    world.set_command(0, 1.0, 1.0)
    values = [world.sensor_values(0)[IR_F2]]
    for _ in range(60):
        world.step()
        values.append(world.sensor_values(0)[IR_F2])
        assert body_centre(world, 0)[0] + world.config.robot_radius <= wall + 1e-12
    assert values[0] == 0.0
    assert all(b >= a for a, b in itertools.pairwise(values))
    # First sight near 14 cm reads about 0.27, as the Thymio's ~1200 of 4500.
    first = next(v for v in values if v > 0)
    assert 0.25 < first < 0.45
    assert values[-1] > 0.95
    # Stopped by the wall: the pose no longer changes.
    before = world.poses.copy()
    world.step()
    np.testing.assert_allclose(world.poses, before, atol=1e-12)


def test_low_walls_are_invisible_to_the_ir_but_still_stop_the_robot():
    world = lone_robot(0.2, 0.0, 0.0)  # the basic arena's walls are low
    world.set_command(0, 1.0, 1.0)
    for _ in range(60):
        world.step()
        assert world.sensor_values(0)[IR_F2] == 0.0
    assert body_centre(world, 0)[0] + world.config.robot_radius == pytest.approx(
        world.config.wall_half
    )


def two_robots(gap: float, where: str = "ahead") -> World:
    # Robot 0 at the origin facing +x; robot 1's body ``gap`` metres from robot 0's sensor.
    world = World(scenario_config("basic", {"robots": 2}), seed=0)
    r, off = world.config.robot_radius, world.config.body_offset
    world.set_pose(0, 0.0, 0.0, 0.0)
    if where == "ahead":
        world.set_pose(1, 0.0795 + gap + r + off, 0.0, math.pi)  # facing back, body nearest
    else:  # behind: the rear sensors sit at x = -0.0295
        world.set_pose(1, -0.0295 - gap - r - off, 0.0, 0.0)
    return world


def ir_value(d: float) -> float:
    c = 0.0073  # Enki's Thymio response c / (d^2 + c), in m^2
    return c / (d * d + c)


@pytest.mark.parametrize("gap", [0.0, 0.02, 0.05, 0.1, 0.13])
def test_the_ir_sees_another_robot_ahead(gap):
    world = two_robots(gap)
    values = world.sensor_values(0)
    assert values[IR_F2] == pytest.approx(ir_value(gap), abs=1e-9)
    if gap <= 0.1:
        assert values[1] > 0 and values[3] > 0  # f1 and f3 see it too, less
    assert values[1] < values[IR_F2] + 1e-12
    assert values[5] == 0.0 and values[6] == 0.0
    # And robot 1, facing robot 0, sees it with its own middle sensor.
    assert world.sensor_values(1)[IR_F2] > 0.25


def test_the_ir_sees_nothing_beyond_its_range():
    world = two_robots(0.15)
    assert world.sensor_values(0)[:7].tolist() == [0.0] * 7


def test_the_rear_sensors_see_a_robot_behind():
    world = two_robots(0.03, where="behind")
    values = world.sensor_values(0)
    assert values[5] > 0.5 and values[6] > 0.5
    assert values[:5].tolist() == [0.0] * 5


def test_a_robot_to_the_left_is_seen_by_the_left_sensors():
    world = World(scenario_config("basic", {"robots": 2}), seed=0)
    world.set_pose(0, 0.0, 0.0, 0.0)
    world.set_pose(1, 0.1, 0.16, 0.0)
    values = world.sensor_values(0)
    assert values[0] > 0.3
    assert values[4] == 0.0


# --- ground and light ------------------------------------------------------------------------


def test_the_ground_sensors_see_the_carpet_edge():
    world = lone_robot(0.3, 0.0, 0.0)
    assert world.sensor_values(0)[7:9].tolist() == [0.4, 0.4]
    world.set_command(0, 0.2, 0.2)
    seen = []
    for _ in range(100):
        world.step()
        x, _, _ = world.poses[0]
        ground = world.sensor_values(0)[7:9]
        sensor_x = x + 0.072
        expected = 0.4 if sensor_x <= 0.5 else 0.95
        assert ground.tolist() == [expected, expected]
        seen.append(expected)
    assert seen[0] == 0.4 and seen[-1] == 0.95


def test_one_ground_sensor_over_the_edge():
    # Heading along the edge, the left sensor (y + 1.2 cm) is beyond y = 0.5, the right is not.
    world = lone_robot(0.0, 0.5 - 0.006, 0.0)
    assert world.sensor_values(0)[7:9].tolist() == [0.95, 0.4]


def test_light_gradient_is_brightest_under_the_lamp_and_dim_in_the_corners():
    world = World(scenario_config("gradient", {"robots": 1}), seed=0)
    light = [world.sensors.index("light.0"), world.sensors.index("light.1")]
    world.set_pose(0, 0.0, 0.0, 0.0)
    centre = world.sensor_values(0)[light]
    assert centre.min() > 0.95
    world.set_pose(0, 0.55, 0.55, math.pi / 4)
    corner = world.sensor_values(0)[light]
    assert 0.07 < corner.max() < 0.13
    # Facing the lamp sideways, the sensor nearer to it reads more.
    world.set_pose(0, 0.3, 0.0, math.pi / 2)  # facing +y, its left (light.0) towards the lamp
    side = world.sensor_values(0)[light]
    assert side[0] > side[1]
    assert world.light_at(0.0, 0.0) == pytest.approx(1.0)
    assert world.light_at(0.55, 0.55) == pytest.approx(0.1)


def test_uniform_light_without_a_lamp():
    world = World(scenario_config("boxes", {"robots": 1, "sensors": list(ALL_SENSORS)}), seed=0)
    assert world.sensor_values(0)[-2:].tolist() == [0.5, 0.5]


def test_values_come_in_the_configured_order():
    world = lone_robot(0.3, 0.0, 0.0, sensors=["ground.1", "ir.f2", "light.0"])
    assert world.sensors == ("ground.1", "ir.f2", "light.0")
    assert world.sensor_values(0).tolist() == [0.4, 0.0, 0.5]


def test_noise_is_gaussian_clipped_and_seeded():
    clean = lone_robot()
    noisy = lone_robot(noise=0.05)
    again = lone_robot(noise=0.05)
    samples = []
    for _ in range(200):
        samples.append(noisy.sensor_values(0) - clean.sensor_values(0))
        assert np.array_equal(noisy.sensor_values(0), again.sensor_values(0))
        assert noisy.sensor_values(0).min() >= 0.0 and noisy.sensor_values(0).max() <= 1.0
        for w in (clean, noisy, again):
            w.step()
    ground = np.array(samples)[:, 7:9]  # 0.4: far from the clipping bounds
    assert ground.std() == pytest.approx(0.05, rel=0.15)
    assert abs(ground.mean()) < 0.01


def test_the_noise_is_the_normal_quantile_of_hashed_uniforms():
    # The generator's quantile against scipy's, over the whole range of the 2^32 uniforms it
    # draws (tails included); its draws have the normal's moments and tail shares.
    stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(0)
    tails = (np.arange(1, 3000) + 0.5) / 2**32
    p = np.concatenate([rng.uniform(0.0, 1.0, 20_000), tails, 1.0 - tails, [0.075, 0.925]])
    ours = np.array([normal_quantile(x) for x in p])
    assert np.allclose(ours, stats.norm.ppf(p), rtol=1e-14, atol=1e-14)
    keys = itertools.product(range(400), range(10), range(12))
    draws = np.array([gaussian(7, t, r, c) for t, r, c in keys])
    assert abs(draws.mean()) < 0.03 and draws.std() == pytest.approx(1.0, abs=0.02)
    assert np.mean(np.abs(draws) > 1.96) == pytest.approx(0.05, abs=0.006)
    assert stats.kstest(draws, "norm").pvalue > 0.01


def test_sensor_values_are_computed_once_per_step():
    world = World(scenario_config("basic"), seed=3)
    first = world.sensor_matrix()
    assert world.sensor_matrix() is first
    world.step()
    assert world.sensor_matrix() is not first


# --- start poses, determinism, recording -----------------------------------------------------


@pytest.mark.parametrize("seed", range(5))
def test_random_starts_are_apart_and_on_the_carpet(seed):
    world = World(scenario_config("basic", {"arena_side": 0.7}), seed=seed)
    centres = np.array([body_centre(world, i) for i in range(10)])
    gaps = np.hypot(*(centres[:, None] - centres[None]).transpose(2, 0, 1)) + np.eye(10)
    assert gaps.min() >= 2 * world.config.robot_radius
    assert np.abs(centres).max() <= 0.35 - world.config.robot_radius + 1e-12


def test_centre_start_is_fixed_whatever_the_seed():
    a = World(scenario_config("boxes"), seed=1)
    b = World(scenario_config("boxes"), seed=2)
    assert np.array_equal(a.poses, b.poses)
    assert np.hypot(a.poses[:, 0], a.poses[:, 1]).max() < 0.2
    assert not np.array_equal(a.box_positions, b.box_positions)


def run(world: World, steps: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    world.start_recording()
    for k in range(steps):
        if k % 7 == 0:
            world.set_commands(rng.uniform(-1, 1, size=(world.n_robots, 2)))
        world.step()
        world.sensor_matrix()
    return world.stop_recording()


@pytest.mark.parametrize("scenario", ["basic", "gradient"])
def test_the_same_seed_gives_the_same_run_bit_for_bit(scenario):
    cfg = scenario_config(scenario, {"noise": 0.02})
    a, b = World(cfg, seed=11), World(cfg, seed=11)
    ta, tb = run(a, 300, 5), run(b, 300, 5)
    assert ta.shape == (301, cfg.robots, 3)
    assert np.array_equal(ta, tb)
    assert np.array_equal(a.box_positions, b.box_positions)
    assert np.array_equal(a.sensor_matrix(), b.sensor_matrix())
    other = World(cfg, seed=12)
    assert not np.array_equal(run(other, 300, 5), ta)


def test_reset_puts_everything_back():
    world = World(scenario_config("gradient"), seed=4)
    poses, boxes = world.poses.copy(), world.box_positions.copy()
    run(world, 100, 0)
    assert not np.array_equal(world.box_positions, boxes)
    world.reset()
    assert world.steps == 0 and world.time == 0.0
    assert np.array_equal(world.poses, poses)
    assert np.array_equal(world.box_positions, boxes)
    assert world.commands.tolist() == [[0.0, 0.0]] * 4
    world.reset(seed=5)
    assert not np.array_equal(world.box_positions, boxes)


def test_recording_keeps_every_step():
    world = World(scenario_config("basic", {"robots": 3}), seed=0, record=True)
    for _ in range(5):
        world.step()
    rec = world.recorded_poses()
    assert rec.shape == (6, 3, 3)
    assert np.array_equal(rec[-1], world.poses)
