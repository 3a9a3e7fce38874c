"""Where robots and boxes start: a random, ring or fixed start of the robots and the boxes'
random or grid layout, drawn from numpy generators seeded by the world's seed (docs/arenas.md).

:class:`~simulator.world.World` calls :func:`place_robots` and :func:`place_boxes` at every reset;
the same seed gives the same start, bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from minimize_surprise.errors import ConfigError
from simulator.scenarios import WorldConfig

__all__ = [
    "TooManyRobotsError",
    "body_reach",
    "place_boxes",
    "place_robots",
    "start_pose_problem",
    "wrap_angle",
]

_TWO_PI = 2.0 * math.pi
# The Thymio II's flat rear is 3 cm behind its wheel axis (docs/simulation.md).
REAR = 0.03
# Placement draws candidate positions in batches of _BATCH, gives up on one robot after
# _MAX_TRIES candidates and on the arena after _PLACEMENT_RESTARTS fresh starts.
_BATCH = 64
_MAX_TRIES = 4_096
_PLACEMENT_RESTARTS = 20


class TooManyRobotsError(ConfigError):
    """More robots than fit at the start: ``robots`` were asked for, at most ``fit`` fit
    ``where`` (e.g. "on a 1.0 m carpet"; ``approximate`` when the random start found that many,
    not a formula); ``larger`` is the world parameter that makes room (``arena_side`` or
    ``start_ring``)."""

    def __init__(self, robots: int, fit: int, where: str, *, larger: str, approximate: bool):
        self.robots = robots
        self.fit = fit
        self.where = where
        self.larger = larger
        self.approximate = approximate
        about = "about " if approximate else ""
        super().__init__(
            f"at most {about}{fit} robots fit {where} ({robots} asked for)",
            key="simulation.robots",
        )


def wrap_angle(theta: np.ndarray | float) -> np.ndarray | float:
    """Angles wrapped to [-pi, pi)."""
    return (theta + math.pi) % _TWO_PI - math.pi


def _ring(gap: float, n: int) -> float:
    # Radius of the ring on which n points stand gap apart from their neighbours.
    return 0.0 if n == 1 else gap / (2 * math.sin(math.pi / n))


def _chord(radius: float, n: int) -> float:
    # Distance between neighbours of n points evenly spread on a ring of that radius.
    return math.inf if n == 1 else 2 * radius * math.sin(math.pi / n)


def _ring_capacity(n: int, fits: Callable[[int], bool]) -> int:
    # The most robots, up to n, that a ring takes; fits(m) is monotone (m robots fit, fewer do).
    return next((m for m in range(n, 0, -1) if fits(m)), 0)


def body_reach(config: WorldConfig) -> float:
    """How far a robot's shapes (body, blade) reach from its body's centre."""
    reach = config.robot_radius
    if config.has_blade:
        rr = config.blade_thickness / 2
        hy = max(config.blade_width / 2 - rr, 0.0) + rr
        off = np.array([-REAR, config.blade_x + rr]) - config.body_offset
        reach = max(reach, float(np.hypot(off, hy).max()))
    return reach


def _carpet(config: WorldConfig) -> tuple[float, float, float, float]:
    # The carpet as a region (x0, y0, x1, y1).
    half_w, half_h = config.carpet_width / 2, config.carpet_height / 2
    return (-half_w, -half_h, half_w, half_h)


def _size(config: WorldConfig) -> str:
    # The carpet's size as a person writes it: "1.0" or "2.2 x 2.9".
    if config.arena_height is None:
        return f"{config.arena_side}"
    return f"{config.carpet_width} x {config.carpet_height}"


def start_pose_problem(config: WorldConfig, poses: np.ndarray) -> str | None:
    """Why the poses (N, 3: x, y, heading in radians) cannot start ``config``'s world: a body
    beyond the carpet or two bodies overlapping; ``None`` when they can."""
    reach = body_reach(config)
    half_w, half_h = config.carpet_width / 2, config.carpet_height / 2
    cx = poses[:, 0] + config.body_offset * np.cos(poses[:, 2])
    cy = poses[:, 1] + config.body_offset * np.sin(poses[:, 2])
    for i in range(len(poses)):
        if abs(cx[i]) + reach > half_w or abs(cy[i]) + reach > half_h:
            return (
                f"the robot at ({poses[i, 0]:g}, {poses[i, 1]:g}) (pose {i + 1}) reaches beyond "
                f"the {_size(config)} m carpet"
            )
        for j in range(i):
            if math.hypot(cx[i] - cx[j], cy[i] - cy[j]) < 2 * config.robot_radius:
                return f"poses {j + 1} and {i + 1} overlap: their bodies would touch at the start"
    return None


def place_robots(config: WorldConfig, rng: np.random.Generator, pose: np.ndarray) -> None:
    """Place ``config``'s robots: their poses into ``pose`` (N, 3), drawn from ``rng``."""
    cfg = config
    n = len(pose)
    rp = body_reach(cfg)
    half = min(cfg.carpet_width, cfg.carpet_height) / 2
    if cfg.start == "fixed":
        _place_fixed(cfg, pose)
        return
    if cfg.start == "centre":
        # A fixed ring around the centre, each robot facing outwards; without a given ring,
        # neighbours just apart.
        phi = _TWO_PI * np.arange(n) / n + math.radians(cfg.start_ring_phase)
        if cfg.start_ring is not None:
            axle = cfg.start_ring
            if axle + cfg.body_offset + rp > half:
                raise ConfigError(
                    "the start ring does not fit in the arena", key="simulation.start_ring"
                )
            # Bodies must not overlap; blades may reach past each other's circle, as in the
            # authors' layout, since they point outwards.
            body = cfg.robot_radius
            fit = _ring_capacity(n, lambda m: _chord(axle + cfg.body_offset, m) >= 2 * body)
            if fit < n:
                raise TooManyRobotsError(
                    n,
                    fit,
                    f"on the start ring {axle} m around the centre",
                    larger="start_ring",
                    approximate=False,
                )
        else:
            gap = 2 * rp + cfg.start_clearance
            fit = _ring_capacity(n, lambda m: _ring(gap, m) + rp <= half)
            if fit == 0:
                raise ConfigError("the arena is too small for a robot", key="simulation.arena_side")
            if fit < n:
                raise TooManyRobotsError(
                    n,
                    fit,
                    f"around the centre of a {cfg.arena_side} m carpet",
                    larger="arena_side",
                    approximate=False,
                )
            axle = _ring(gap, n) - cfg.body_offset
        pose[:, 0] = axle * np.cos(phi)
        pose[:, 1] = axle * np.sin(phi)
        pose[:, 2] = wrap_angle(phi)
        return
    # Random: bodies wholly on the carpet (or the start region), apart by the clearance, in
    # seeded order. Robots placed one by one can box themselves in on a crowded carpet; then
    # all start afresh.
    key = "simulation.arena_side"
    if cfg.start_region is None and cfg.arena_height is None:
        lim: float | tuple[np.ndarray, np.ndarray] = half - rp
        room = half - rp
    else:
        x0, y0, x1, y1 = cfg.start_region or _carpet(cfg)
        lim = (np.array([x0 + rp, y0 + rp]), np.array([x1 - rp, y1 - rp]))
        room = float(np.min(lim[1] - lim[0]))
        key = "simulation.start_region" if cfg.start_region else key
    if room <= 0:
        raise ConfigError("the arena is too small for a robot", key=key)
    min_d2 = (2 * rp + cfg.start_clearance) ** 2
    most = 0
    for _ in range(_PLACEMENT_RESTARTS):
        centres, placed = _random_centres(rng, n, lim, min_d2)
        if placed == n:
            break
        most = max(most, placed)
    else:
        # The most any start placed: with this seed that many would have been placed (a
        # start draws the same candidates whatever the number asked for), with another
        # seed about as many.
        where = (
            f"in the start region {list(cfg.start_region)}"
            if cfg.start_region
            else f"on a {_size(cfg)} m carpet"
        )
        larger = "start_region" if cfg.start_region else "arena_side"
        raise TooManyRobotsError(n, most, where, larger=larger, approximate=True)
    theta = rng.uniform(-math.pi, math.pi, size=n)
    pose[:, 0] = centres[:, 0] - cfg.body_offset * np.cos(theta)
    pose[:, 1] = centres[:, 1] - cfg.body_offset * np.sin(theta)
    pose[:, 2] = theta


def _place_fixed(config: WorldConfig, pose: np.ndarray) -> None:
    # The given poses, checked: on the carpet and apart (the arena file's check names the
    # key; here the experiment's own ``simulation.start_poses`` may have been given).
    cfg = config
    poses = np.array(cfg.start_poses, dtype=float).reshape(-1, 3)
    theta = np.radians(poses[:, 2])
    pose[:, 0] = poses[:, 0]
    pose[:, 1] = poses[:, 1]
    pose[:, 2] = wrap_angle(theta)
    problem = start_pose_problem(cfg, pose)
    if problem:
        raise ConfigError(problem, key="simulation.start_poses")


def _random_centres(
    rng: np.random.Generator,
    n: int,
    lim: float | tuple[np.ndarray, np.ndarray],
    min_d2: float,
) -> tuple[np.ndarray, int]:
    # Body centres in [-lim, lim]^2 (or between the corners lim = (low, high)), pairwise at
    # least sqrt(min_d2) apart, and how many were placed before one found no room (n when
    # all were).
    low, high = (-lim, lim) if isinstance(lim, float) else lim
    placed = np.empty((n, 2))
    for i in range(n):
        for _ in range(_MAX_TRIES // _BATCH):
            cand = rng.uniform(low, high, size=(_BATCH, 2))
            d2 = ((cand[:, None, :] - placed[None, :i, :]) ** 2).sum(axis=2)
            ok = np.flatnonzero((d2 >= min_d2).all(axis=1))
            if ok.size:
                placed[i] = cand[ok[0]]
                break
        else:
            return placed, i
    return placed, n


def place_boxes(config: WorldConfig, rng: np.random.Generator, pose: np.ndarray) -> np.ndarray:
    """The boxes' centres (K, 2) for ``config``, drawn from ``rng``, clear of the robots at
    ``pose``."""
    cfg = config
    if not cfg.boxes:
        return np.zeros((0, 2))
    if cfg.box_layout == "grid":
        return _grid_boxes(cfg, rng)
    count = cfg.box_count
    if count == 0:
        return np.zeros((0, 2))
    rb = cfg.box_size / 2
    if cfg.box_region is None and cfg.arena_height is None:
        low: float | np.ndarray = -(cfg.arena_side / 2 - rb)
        high: float | np.ndarray = cfg.arena_side / 2 - rb
    else:
        x0, y0, x1, y1 = cfg.box_region or _carpet(cfg)
        low, high = np.array([x0 + rb, y0 + rb]), np.array([x1 - rb, y1 - rb])
    rp = body_reach(cfg)
    th = pose[:, 2]
    rcx = pose[:, 0] + cfg.body_offset * np.cos(th)
    rcy = pose[:, 1] + cfg.body_offset * np.sin(th)
    away2 = (rp + rb + cfg.start_clearance) ** 2
    apart2 = (cfg.box_size + 0.001) ** 2
    clear = cfg.box_clear_centre / 2
    out = np.empty((count, 2))
    k = 0
    tries = 0
    while k < count:
        if tries >= 50 * count + _MAX_TRIES:
            key = "box_number" if cfg.box_number is not None else "box_coverage"
            raise ConfigError(
                f"cannot place {count} boxes apart on the carpet", key=f"simulation.{key}"
            )
        cand = rng.uniform(low, high, size=(4 * _BATCH, 2))
        tries += len(cand)
        d2 = (cand[:, 0, None] - rcx) ** 2 + (cand[:, 1, None] - rcy) ** 2
        keep = (d2 >= away2).all(axis=1) & ~(np.abs(cand) < clear).all(axis=1)
        cand = cand[keep]
        # Accept in order, each against every box accepted so far (a one-off cost at set-up).
        for c in cand:
            if k and (((out[:k] - c) ** 2).sum(axis=1) < apart2).any():
                continue
            out[k] = c
            k += 1
            if k == count:
                break
    return out


def _grid_boxes(config: WorldConfig, rng: np.random.Generator) -> np.ndarray:
    # The authors' Webots layout: rows box_grid_pitch apart; along a row each box
    # pitch .. pitch + jitter after the last, up to jitter above the row; every coordinate
    # rounded to 1 cm; none in the central clear square. About 270 boxes on 1.1 m.
    cfg = config
    pitch, jitter = cfg.box_grid_pitch, cfg.box_grid_jitter
    # 1.8 cm in from the carpet's edge (the authors' arenas are square: the shorter side)
    edge = min(cfg.carpet_width, cfg.carpet_height) / 2 - cfg.box_size * 0.72
    clear = cfg.box_clear_centre / 2
    boxes = []
    row = -edge
    x = -edge
    while row <= edge:
        while x <= edge:
            y = round(rng.uniform(row, row + jitter), 2)
            if not (abs(x) < clear and abs(y) < clear) and abs(y) <= edge:
                boxes.append((x, y))
            x = round(rng.uniform(x + pitch, x + pitch + jitter), 2)
        row += pitch
        x = round(rng.uniform(-edge, -edge + pitch), 2)
    return np.array(boxes, dtype=float).reshape(-1, 2)
