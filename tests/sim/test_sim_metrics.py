"""The paper's behaviour metrics on hand-made trajectories (simulator.metrics)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simulator import metrics
from simulator.metrics import (
    behaviour_metrics,
    box_displacement,
    classify_grouping,
    classify_motion,
    cluster_counts,
    default_window,
    distance_covered,
    mean_cluster_size,
    rotation,
)


def still(positions, steps: int = 10, theta: float = 0.0) -> np.ndarray:
    """Robots standing at ``positions`` (N, 2) for ``steps`` steps: shape (steps + 1, N, 3)."""
    pos = np.asarray(positions, dtype=float)
    poses = np.zeros((steps + 1, len(pos), 3))
    poses[:, :, :2] = pos
    poses[:, :, 2] = theta
    return poses


def test_distance_covered_is_the_mean_path_length():
    poses = still([[0, 0], [1, 1]], steps=100)
    poses[:, 0, 0] = np.arange(101) * 0.01  # robot 0 drives 1 m; robot 1 stands
    assert distance_covered(poses) == pytest.approx(0.5)
    # A back-and-forth path counts both ways.
    poses[:, 1, 1] = 1 + 0.01 * (np.arange(101) % 2)
    assert distance_covered(poses) == pytest.approx((1.0 + 1.0) / 2)
    assert distance_covered(poses, window=10) == pytest.approx((0.1 + 0.1) / 2)


def test_rotation_accumulates_wrapped_heading_changes():
    poses = still([[0, 0], [1, 0]], steps=100)
    # Both turn +0.1 rad per step, crossing +-pi several times.
    theta = (np.arange(101) * 0.1 + math.pi) % (2 * math.pi) - math.pi
    poses[:, :, 2] = theta[:, None]
    assert rotation(poses) == pytest.approx(10.0)
    assert rotation(poses, window=20) == pytest.approx(2.0)


def test_rotation_is_the_absolute_value_of_the_swarm_sum():
    poses = still([[0, 0], [1, 0]], steps=50)
    poses[:, 0, 2] = np.arange(51) * 0.05
    poses[:, 1, 2] = -np.arange(51) * 0.05
    assert rotation(poses) == pytest.approx(0.0, abs=1e-12)
    assert rotation(poses, each_step=True) == pytest.approx(2.5)
    poses[:, 1, 2] = 0.0
    assert rotation(poses) == pytest.approx(2.5 / 2)
    # To and fro: the sum cancels, the steps do not.
    poses[:, 0, 2] = 0.1 * (np.arange(51) % 2)
    assert rotation(poses) == pytest.approx(0.0, abs=1e-12)
    assert rotation(poses, each_step=True) == pytest.approx(50 * 0.1 / 2)


def test_a_robot_circling_at_full_speed_for_50_s_turns_about_126_rad():
    steps, rate = 500, 2 * 0.126 / 0.1  # paper: 126 rad with a 10 cm wheel base
    theta = (np.arange(steps + 1) * rate * 0.1 + math.pi) % (2 * math.pi) - math.pi
    poses = still([[0, 0]], steps=steps)
    poses[:, 0, 2] = theta
    assert rotation(poses) == pytest.approx(126.0)
    assert classify_motion(rotation(poses)) == "circling"


def test_clusters_link_robots_within_two_radii_transitively():
    # A chain of three (15 cm apart, the ends 30 cm apart), a pair, and five loners.
    chain_and_pair = [[0, 0], [0.15, 0], [0.30, 0], [1, 1], [1, 1.1]]
    loners = [[-1, -1], [-1, 1], [1, -1], [2, 2], [-2, -2]]
    positions = np.array([*chain_and_pair, *loners], dtype=float)
    assert cluster_counts(positions).tolist() == [7]
    assert mean_cluster_size(still(positions)) == pytest.approx(10 / 7)
    # Beyond 15.75 cm the chain falls apart.
    positions[1, 0] = 0.16
    positions[2, 0] = 0.32
    assert cluster_counts(positions).tolist() == [9]


def test_mean_cluster_size_is_averaged_over_the_window():
    poses = still([[0, 0], [0.1, 0], [1, 0], [2, 0]], steps=3)
    poses[2:, 1, 0] = 0.5  # robot 1 leaves robot 0 after the first step
    # instants: 4/3, 4/3, 4/4, 4/4
    assert mean_cluster_size(poses) == pytest.approx((4 / 3 * 2 + 1 + 1) / 4)
    assert mean_cluster_size(poses, window=1) == pytest.approx(1.0)
    assert mean_cluster_size(poses, window=0) == pytest.approx(1.0)


def test_box_displacement_is_the_mean_start_to_end_distance():
    start = np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]])
    end = start + np.array([[0.3, 0.4], [0.0, 0.0], [-0.6, 0.8]])
    assert box_displacement(start, end) == pytest.approx((0.5 + 0.0 + 1.0) / 3)
    assert box_displacement(np.zeros((0, 2)), np.zeros((0, 2))) == 0.0
    with pytest.raises(ValueError):
        box_displacement(start, end[:2])


@pytest.mark.parametrize(
    ("c_o", "motion"),
    [(0.0, "stopped"), (4.99, "stopped"), (5.0, "diverse"), (55.0, "diverse"), (55.1, "circling")],
)
def test_motion_classes(c_o, motion):
    assert classify_motion(c_o) == motion


@pytest.mark.parametrize(
    ("size", "grouping"), [(1.0, "dispersed"), (1.43, "dispersed"), (1.44, "grouped")]
)
def test_grouping_classes(size, grouping):
    assert classify_grouping(size) == grouping


def test_behaviour_metrics_of_ten_stopped_robots_in_pairs_pushing_boxes():
    pairs = [[x, y] for x in range(5) for y in (0.0, 0.1)]
    poses = still(pairs, steps=1000)
    start = np.zeros((4, 2))
    end = np.array([[0.2, 0.0], [0.0, 0.2], [0.0, 0.0], [0.0, 0.0]])
    m = behaviour_metrics(poses, start, end)
    assert m.window == 500
    assert m.distance_covered == 0.0
    assert m.rotation == 0.0
    assert m.mean_cluster_size == pytest.approx(2.0)
    assert m.box_displacement == pytest.approx(0.1)
    assert (m.motion, m.grouping, m.pushing) == ("stopped", "grouped", False)
    assert behaviour_metrics(poses).pushing is None


def test_behaviour_metrics_of_robots_circling_apart():
    steps = 1000
    poses = still([[0, 0], [1, 0], [0, 1], [1, 1]], steps=steps)
    theta = (np.arange(steps + 1) * 0.3 + math.pi) % (2 * math.pi) - math.pi
    poses[:, :, 2] = theta[:, None]
    m = behaviour_metrics(poses, window=500)
    assert m.rotation == pytest.approx(150.0)
    assert (m.motion, m.grouping) == ("circling", "dispersed")
    assert m.mean_cluster_size == 1.0


def test_the_default_window_is_50_s_or_the_second_half():
    assert default_window(np.zeros((1001, 2, 3))) == metrics.DEFAULT_WINDOW == 500
    assert default_window(np.zeros((101, 2, 3))) == 50
    assert default_window(np.zeros((2, 2, 3))) == 1


def test_poses_must_have_the_right_shape():
    with pytest.raises(ValueError, match="shape"):
        rotation(np.zeros((10, 3)))


@pytest.mark.parametrize("robots", [3, 40, 1000])
def test_clusters_of_a_large_swarm_are_those_of_its_whole_linkage_graph(robots):
    # Every pair compared, the graph's connected components counted by scipy: what the grid
    # (which compares only neighbouring cells) must find, here at about the basic density and
    # twice it, robots exactly 15.75 cm apart linked, a NaN robot alone.
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(robots)
    side = math.sqrt(robots / 10)
    positions = rng.uniform(-side / 2, side / 2, size=(6, robots, 2))
    positions[3:] *= 0.7
    positions[5, 1] = positions[5, 0] + [metrics.CLUSTER_DISTANCE, 0.0]
    positions[4, 0] = np.nan
    expected = []
    for instant in positions:
        d2 = ((instant[:, None] - instant[None]) ** 2).sum(axis=2)
        linked = d2 <= metrics.CLUSTER_DISTANCE**2
        expected.append(connected_components(linked, directed=False)[0])
    assert cluster_counts(positions).tolist() == expected
    assert min(expected) < robots  # some robots were linked


def test_the_trace_features_turn_rate_still_share_and_neighbour_distance():
    # Two robots 0.5 m apart turning on the spot opposite ways at 1 rad/s for 10 steps of 0.1 s:
    # c_o cancels, the turn rate does not; nobody moves, and the nearest neighbour is 0.5 m away.
    poses = still([[0.0, 0.0], [0.5, 0.0]], steps=10)
    poses[:, 0, 2] = np.arange(11) * 0.1
    poses[:, 1, 2] = -np.arange(11) * 0.1
    assert rotation(poses) == pytest.approx(0.0, abs=1e-12)
    assert metrics.turn_rate(poses, dt=0.1) == pytest.approx(1.0)
    assert metrics.still_share(poses, dt=0.1) == 1.0
    assert metrics.neighbour_distance(poses) == pytest.approx(0.5)
    # One robot drives at 5 cm/s (moving), the other stays: half the robot-steps are still.
    poses[:, 0, 0] = np.arange(11) * 0.005
    assert metrics.still_share(poses, dt=0.1) == pytest.approx(0.5)
    assert metrics.neighbour_distance(still([[0.0, 0.0]])) is None
    m = behaviour_metrics(poses, window=10, dt=0.1)
    assert m.turn_rate == pytest.approx(1.0) and m.still_share == pytest.approx(0.5)
    assert m.neighbour_distance == pytest.approx(np.mean(0.5 - np.arange(11) * 0.005))
