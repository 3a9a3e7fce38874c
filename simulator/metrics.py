"""The paper's behaviour metrics (Sec. V; docs/method.md), computed from recorded poses.

``poses`` is an array of shape (T + 1, N, 3): the ``x, y, theta`` of N robots at T + 1 instants
(as :meth:`simulator.world.World.recorded_poses` returns), in metres and radians.

* distance covered d_R: mean over robots of the path length (sum of step displacements);
* box displacement d_B: mean distance between the boxes' start and end positions;
* rotation c_o: ``|1/N sum_n sum_t (theta_n(t+1) - theta_n(t))|`` over the last ``window`` steps,
  each step's change wrapped to [-pi, pi) (paper Eq. for c_o; 126 rad is constant turning at full
  speed for 50 s). The absolute value is taken of the swarm's sum, as in the paper, so robots
  turning opposite ways cancel;
* mean cluster size: robots closer than ``cluster_distance`` (2 robot radii, about 15.75 cm, between
  positions) to another member share a cluster (single linkage); the mean cluster size of one
  instant is N / (number of clusters), and the metric is its mean over the instants of the window.

* backward share: of the robots' steps that moved them (more than :data:`MOVING_ABOVE`), the share
  that moved them backwards (against their heading), over the whole recording.

Three more features of the trace, which no class of the paper uses: they are for the study's
clustering without thresholds (docs/studies.md), over the same window as c_o:

* turn rate: mean absolute heading change per robot per second (robots turning opposite ways,
  or to and fro, do not cancel, as they do in c_o);
* still share: the share of robot-steps slower than :data:`STILL_BELOW`;
* neighbour distance: mean over instants and robots of the distance to the nearest other robot.

Classification (paper Sec. V-B, V-C): stopped if c_o < 5, circling if c_o > 55, else diverse;
grouped if the mean cluster size exceeds 1.43, else dispersed; pushing if d_B > 0.1 m. With boxes
(object manipulation, Sec. V-C) each run also gets one of the paper's three classes
(:func:`classify_manipulation`): pushing when d_B > 0.1 m, else reverse driving when most of the
moving steps went backwards and the swarm is not circling, else circling (the paper's majority
class, which takes every other run, robots circling backwards included). The
thresholds were chosen for windows of 50 s (5000 Webots steps of 10 ms); our 10 Hz window of the
same length is 500 steps, the default below when the recording is long enough (else its second
half).
"""

from __future__ import annotations

import math
from typing import Literal

import msgspec
import numpy as np

from minimize_surprise.jit import kernel
from minimize_surprise.precompile import Plan, signature
from simulator.physics.grid import build, gather, grid_side, new_cells

#: Robots closer than this (metres, between positions) are in one cluster (paper: 15.75 cm).
CLUSTER_DISTANCE = 0.1575
#: Classification thresholds of the paper.
STOPPED_BELOW = 5.0
CIRCLING_ABOVE = 55.0
GROUPED_ABOVE = 1.43
PUSHING_ABOVE = 0.1
#: The length of the paper's analysis window in seconds: the last 5000 of 10,000 steps of 10 ms.
WINDOW_SECONDS = 50.0
#: That window in steps at the real robots' 10 Hz.
DEFAULT_WINDOW = 500
#: A step that moved a robot less than this (metres) did not move it: turning on the spot, or held
#: by the safety layer. A robot at 1 cm/s moves 0.1 mm in a 10 ms step, ten times this.
MOVING_ABOVE = 1e-5
#: A robot slower than this (m/s) stands still for the still share: a tenth of the real robots'
#: top speed (10.6 cm/s), above the drift of a robot that the safety layer holds.
STILL_BELOW = 0.01
#: Reverse driving when more than this share of the moving steps went backwards.
REVERSE_ABOVE = 0.5
#: The object-manipulation classes of the paper (Sec. V-C), one per run.
Manipulation = Literal["pushing", "reverse driving", "circling"]


class BehaviourMetrics(msgspec.Struct, frozen=True, kw_only=True):
    """The metrics of one run and their classification (``pushing`` is None without boxes)."""

    distance_covered: float
    rotation: float
    mean_cluster_size: float
    box_displacement: float | None
    motion: Literal["stopped", "diverse", "circling"]
    grouping: Literal["grouped", "dispersed"]
    pushing: bool | None
    window: int
    #: share of the moving steps that went backwards (see the module docstring)
    backward_share: float | None = None
    #: with boxes, the paper's object-manipulation class of the run; None without boxes
    manipulation: Manipulation | None = None
    #: mean absolute heading change per robot, rad/s, over the window (None: written before)
    turn_rate: float | None = None
    #: share of the window's robot-steps slower than :data:`STILL_BELOW`
    still_share: float | None = None
    #: mean distance to the nearest other robot over the window, metres (None: one robot)
    neighbour_distance: float | None = None


def _check(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 3 or poses.shape[2] != 3 or poses.shape[0] < 1:
        raise ValueError(f"poses must have shape (T + 1, N, 3), not {poses.shape}")
    return poses


def _window(poses: np.ndarray, window: int | None) -> np.ndarray:
    # The last ``window`` steps, i.e. the last window + 1 instants.
    if window is None:
        return poses
    if window < 0:
        raise ValueError("window must be >= 0")
    return poses[max(len(poses) - 1 - window, 0) :]


def default_window(poses: np.ndarray, dt: float = 0.1) -> int:
    """The paper's 50 s window (500 steps of 0.1 s, 5000 of 10 ms) if the recording of steps of
    ``dt`` seconds holds twice that, else its second half: the first half gives the robots time
    to settle into their behaviour."""
    steps = len(poses) - 1
    window = round(WINDOW_SECONDS / dt)
    return window if steps >= 2 * window else steps - steps // 2


def distance_covered(poses: np.ndarray, window: int | None = None) -> float:
    """d_R: mean path length per robot over the last ``window`` steps (all if None), metres."""
    p = _window(_check(poses), window)
    if len(p) < 2:
        return 0.0
    steps = np.hypot(np.diff(p[:, :, 0], axis=0), np.diff(p[:, :, 1], axis=0))
    return float(steps.sum(axis=0).mean())


def box_displacement(start: np.ndarray, end: np.ndarray) -> float:
    """d_B: mean distance between the boxes' ``start`` and ``end`` positions (B, 2), metres."""
    start = np.asarray(start, dtype=float).reshape(-1, 2)
    end = np.asarray(end, dtype=float).reshape(-1, 2)
    if start.shape != end.shape:
        raise ValueError(f"start {start.shape} and end {end.shape} differ in shape")
    if len(start) == 0:
        return 0.0
    return float(np.hypot(*(end - start).T).mean())


def rotation(poses: np.ndarray, window: int | None = None, *, each_step: bool = False) -> float:
    """c_o: absolute accumulated heading change per robot over the last ``window`` steps, rad.

    By default the paper's equation: the absolute value of the swarm's summed change, divided by
    N. ``each_step=True`` sums the absolute value of every step's change instead, so that robots
    turning opposite ways, or to and fro, do not cancel.
    """
    p = _window(_check(poses), window)
    if len(p) < 2:
        return 0.0
    turn = (np.diff(p[:, :, 2], axis=0) + math.pi) % (2 * math.pi) - math.pi
    if each_step:
        return float(np.abs(turn).sum() / p.shape[1])
    return float(abs(turn.sum() / p.shape[1]))


def cluster_counts(positions: np.ndarray, distance: float = CLUSTER_DISTANCE) -> np.ndarray:
    """Number of clusters at each instant of ``positions`` (T, N, 2) (or one instant (N, 2)).

    Robots are linked when their positions are at most ``distance`` apart and clusters are the
    linked groups (single linkage, found by union-find). Only robots in neighbouring cells of a
    grid at least ``distance`` wide are compared (.physics.grid), so a thousand robots cost a
    thousand times what one costs, not a million; a robot at NaN is a cluster of its own.
    """
    pos = np.asarray(positions, dtype=float)
    if pos.ndim == 2:
        pos = pos[None]
    finite = np.abs(pos[np.isfinite(pos)])
    # The grid covers every position, with room to spare so that none is at its edge.
    half = (float(finite.max()) if finite.size else 0.0) + distance
    return _count_clusters(np.ascontiguousarray(pos[:, :, :2]), float(distance), half)


def compile_plan() -> Plan:
    """The measures' kernels with the signatures :func:`cluster_counts` calls them with: for
    :func:`~minimize_surprise.precompile.compile_ahead`, before a run reports its behaviour."""
    return [(_count_clusters, signature(_count_clusters, np.zeros((1, 1, 2)), 0.0, 0.0))]


@kernel
def _count_clusters(pos: np.ndarray, distance: float, half: float) -> np.ndarray:
    steps, n = pos.shape[0], pos.shape[1]
    side = grid_side(half, distance, n)
    cells = new_cells(n, side)
    cell, start, order = cells.cell, cells.start, cells.order
    near = np.empty(n, dtype=np.int64)
    parent = np.empty(n, dtype=np.int64)
    reach2 = distance * distance
    counts = np.empty(steps, dtype=np.int64)
    for t in range(steps):
        build(pos[t, :, 0], pos[t, :, 1], half, side, cell, start, order)
        for i in range(n):
            parent[i] = i
        clusters = n
        for i in range(n):
            for q in range(gather(i, side, cell, start, order, near, False)):
                j = near[q]
                if j <= i:
                    continue
                dx = pos[t, i, 0] - pos[t, j, 0]
                dy = pos[t, i, 1] - pos[t, j, 1]
                if dx * dx + dy * dy <= reach2:
                    a, b = _root(parent, i), _root(parent, j)
                    if a != b:
                        parent[max(a, b)] = min(a, b)
                        clusters -= 1
        counts[t] = clusters
    return counts


@kernel
def _root(parent: np.ndarray, i: int) -> int:
    # The root of i's tree, halving the path on the way (every other node to its grandparent).
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def mean_cluster_size(
    poses: np.ndarray, window: int | None = None, distance: float = CLUSTER_DISTANCE
) -> float:
    """Mean over the instants of the last ``window`` steps of N / (number of clusters)."""
    p = _window(_check(poses), window)
    counts = cluster_counts(p[:, :, :2], distance)
    return float((p.shape[1] / counts).mean())


def behaviour_metrics(
    poses: np.ndarray,
    box_start: np.ndarray | None = None,
    box_end: np.ndarray | None = None,
    *,
    window: int | None = None,
    cluster_distance: float = CLUSTER_DISTANCE,
    dt: float = 0.1,
) -> BehaviourMetrics:
    """Every metric and its class. d_R and d_B cover the whole recording (the paper's Eq. for
    d_R sums over the run); c_o and the cluster size the last ``window`` steps (default:
    :func:`default_window` for steps of ``dt`` seconds). Boxes are optional."""
    poses = _check(poses)
    if window is None:
        window = default_window(poses, dt)
    c_o = rotation(poses, window)
    size = mean_cluster_size(poses, window, cluster_distance)
    d_b = None if box_start is None or box_end is None else box_displacement(box_start, box_end)
    backward = backward_share(poses)
    motion = classify_motion(c_o)
    recent = _window(poses, window)
    return BehaviourMetrics(
        distance_covered=distance_covered(poses),
        rotation=c_o,
        mean_cluster_size=size,
        box_displacement=d_b,
        motion=motion,
        grouping=classify_grouping(size),
        pushing=None if d_b is None else d_b > PUSHING_ABOVE,
        window=window,
        backward_share=backward,
        manipulation=None if d_b is None else classify_manipulation(d_b, backward, motion),
        turn_rate=turn_rate(recent, dt),
        still_share=still_share(recent, dt),
        neighbour_distance=neighbour_distance(recent),
    )


def turn_rate(poses: np.ndarray, dt: float = 0.1) -> float:
    """Mean absolute heading change per robot per second over ``poses``' steps of ``dt`` s."""
    poses = _check(poses)
    steps = len(poses) - 1
    return rotation(poses, each_step=True) / (steps * dt) if steps else 0.0


def still_share(poses: np.ndarray, dt: float = 0.1) -> float:
    """The share of ``poses``' robot-steps (of ``dt`` s) slower than :data:`STILL_BELOW`."""
    poses = _check(poses)
    if len(poses) < 2:
        return 1.0
    speed = np.hypot(*np.diff(poses[:, :, :2], axis=0).transpose(2, 0, 1)) / dt
    return float((speed < STILL_BELOW).mean())


def neighbour_distance(poses: np.ndarray) -> float | None:
    """Mean over ``poses``' instants and robots of the distance to the nearest other robot,
    metres; None for one robot."""
    poses = _check(poses)
    if poses.shape[1] < 2:
        return None
    xy = poses[:, :, :2]
    gaps = np.linalg.norm(xy[:, :, None, :] - xy[:, None, :, :], axis=-1)
    robots = poses.shape[1]
    gaps[:, np.arange(robots), np.arange(robots)] = np.inf
    return float(gaps.min(axis=2).mean())


def backward_share(poses: np.ndarray) -> float:
    """Of the robot-steps that moved a robot, the share that moved it backwards: the step's
    displacement against the heading it had at the step's start. 0 when nothing moved."""
    poses = _check(poses)
    step = np.diff(poses[:, :, :2], axis=0)
    heading = poses[:-1, :, 2]
    forward = step[..., 0] * np.cos(heading) + step[..., 1] * np.sin(heading)
    moving = np.abs(forward) > MOVING_ABOVE
    count = int(moving.sum())
    return float((forward[moving] < 0).sum() / count) if count else 0.0


def classify_manipulation(d_b: float, backward: float, motion: str) -> Manipulation:
    """The paper's object-manipulation class (Sec. V-C): pushing when the boxes moved more than
    0.1 m on average; else reverse driving when most moving steps went backwards and the swarm
    does not circle (the paper's reverse drivers "drive backwards until they are stopped by
    hardware protection"; robots going round small circles backwards are circling, as the
    paper classed what it saw); else circling."""
    if d_b > PUSHING_ABOVE:
        return "pushing"
    if backward > REVERSE_ABOVE and motion != "circling":
        return "reverse driving"
    return "circling"


def behaviour_label(behaviour: dict[str, object] | BehaviourMetrics, sep: str = ", ") -> str:
    """A run's behaviour in words: the object-manipulation class with boxes (the motion and
    grouping in brackets), else ``motion, grouping``."""
    b = msgspec.to_builtins(behaviour) if isinstance(behaviour, BehaviourMetrics) else behaviour
    kind = f"{b['motion']}{sep}{b['grouping']}"
    manipulation = b.get("manipulation")
    if manipulation is None and b.get("box_displacement") is not None:
        # A run's metrics written before the classes existed: pushing or not.
        return kind + (f"{sep}pushing" if b.get("pushing") else f"{sep}not pushing")
    return kind if manipulation is None else f"{manipulation} ({kind})"


def classify_motion(c_o: float) -> Literal["stopped", "diverse", "circling"]:
    """Stopped below 5 rad, circling above 55 rad, diverse between (paper Sec. V-B)."""
    if c_o < STOPPED_BELOW:
        return "stopped"
    if c_o > CIRCLING_ABOVE:
        return "circling"
    return "diverse"


def classify_grouping(mean_size: float) -> Literal["grouped", "dispersed"]:
    """Grouped when the mean cluster size exceeds 1.43 (paper Sec. V-B)."""
    return "grouped" if mean_size > GROUPED_ABOVE else "dispersed"
