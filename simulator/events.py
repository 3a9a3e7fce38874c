"""What an experiment's events (``minimize_surprise.events``) do to a simulated world.

Each change happens between two evaluations, on the world as the last evaluation left it:

* ``light-moves``: the lamp is above another point; the light sensors read the new gradient.
* ``boxes-added``: boxes at random places of the region, clear of every robot and box (drawn
  from a generator seeded by the experiment's seed and the event's index, so a run is repeatable).
* ``boxes-removed``: the boxes placed last are taken away.
* ``wall-appears``: a line of boxes, side by side, along the segment. The physics' walls are the
  rectangle around the floor, and the contact and IR kernels test it with four comparisons; an
  interior wall would add a case to every one of them in the hottest loops, so the wall is made
  of what the kernels already move: boxes. Robots push such a wall as they push boxes
  (docs/changing-arenas.md says so), and IR does not see boxes.
* ``robots-leave`` / ``robots-join`` (the engine's swarm): the last robots of the swarm are taken
  out of the world; new ones are placed at random places clear of the other robots, idle, with
  fresh safety layers (boxes under one are pushed off it by the next step's box physics).
  The swarm's fitness is the mean over the robots that evaluated.

:func:`check_arena_events` refuses, by key, what the arena cannot hold.
"""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import numpy as np

from minimize_surprise.errors import ConfigError
from minimize_surprise.events import (
    ArenaEvent,
    BoxesAdded,
    BoxesRemoved,
    LightMoves,
    RobotsJoin,
    RobotsLeave,
    WallAppears,
    describe,
)
from simulator.placement import body_reach
from simulator.scenarios import WorldConfig
from simulator.world import World

__all__ = ["apply_to_world", "check_arena_events", "event_rng", "wall_boxes"]

#: Random candidates drawn for each box or robot to place before giving up.
_TRIES = 2000


def event_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of the experiment's event ``index`` (seeded by the experiment's seed)."""
    return np.random.default_rng(np.random.SeedSequence([seed, 0xE7E1, index]))


def wall_boxes(event: WallAppears, box_size: float) -> np.ndarray:
    """The centres (K, 2) of the boxes that make the wall of ``event``, side by side."""
    (x0, y0), (x1, y1) = event.start, event.end
    length = math.hypot(x1 - x0, y1 - y0)
    # A millimetre apart, as random placement keeps them: boxes that touch count as overlapping.
    count = max(1, math.floor(length / (box_size + 0.001)))
    t = (np.arange(count) + 0.5) / count
    return np.stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0)], axis=1)


def check_arena_events(
    events: list[ArenaEvent], config: WorldConfig, *, file: str | Path | None = None
) -> None:
    """Raise ConfigError naming ``file`` and the key of the first event the world of ``config``
    cannot take: a point off the floor, more boxes removed than there are, a lamp to move in
    an arena without one."""
    half_w, half_h = config.carpet_width / 2, config.carpet_height / 2
    boxes = config.box_count if config.boxes else 0
    where = str(file) if file else None

    def refuse(key: str, text: str) -> ConfigError:
        return ConfigError(text, file=where, key=key)

    def on_floor(key: str, x: float, y: float) -> None:
        if not (math.isfinite(x) and math.isfinite(y)) or abs(x) > half_w or abs(y) > half_h:
            raise refuse(
                key,
                f"({x:g}, {y:g}) is outside the {2 * half_w:g} x {2 * half_h:g} m floor",
            )

    for i in sorted(range(len(events)), key=lambda i: _order(events[i])):
        event, key = events[i], f"events[{i}]"
        if isinstance(event, LightMoves):
            if not config.light:
                raise refuse(f"{key}.kind", "the light can only move in an arena with a lamp")
            on_floor(f"{key}.position", *event.position)
        elif isinstance(event, BoxesAdded):
            if event.region is not None:
                x0, y0, x1, y1 = event.region
                if not (x0 < x1 and y0 < y1):
                    raise refuse(f"{key}.region", "expected [x0, y0, x1, y1], x0 < x1, y0 < y1")
                on_floor(f"{key}.region", x0, y0)
                on_floor(f"{key}.region", x1, y1)
            boxes += event.count
        elif isinstance(event, BoxesRemoved):
            if event.count is not None and event.count > boxes:
                raise refuse(
                    f"{key}.count",
                    f"{event.count} boxes cannot be removed: the arena has {boxes} then",
                )
            boxes = 0 if event.all else boxes - (event.count or 0)
        elif isinstance(event, WallAppears):
            on_floor(f"{key}.start", *event.start)
            on_floor(f"{key}.end", *event.end)
            boxes += len(wall_boxes(event, config.box_size))


def _order(event: ArenaEvent) -> tuple[int, float]:
    # Events by evaluation, then those by time (which come when they come).
    if event.evaluation is not None:
        return 0, float(event.evaluation)
    return 1, float(event.seconds or 0.0)


def apply_to_world(
    world: World, event: ArenaEvent, rng: np.random.Generator
) -> tuple[list[int], int]:
    """Change ``world`` as ``event`` says; for robots leaving or joining, the indexes of the
    robots that stay, in order, and how many joined after them (else every robot, 0)."""
    config = world.config
    everyone = list(range(world.n_robots))
    if isinstance(event, LightMoves):
        world.reconfigure(msgspec.structs.replace(config, light_position=event.position))
    elif isinstance(event, BoxesAdded):
        world.add_boxes(_free_boxes(world, event.count, event.region, rng))
    elif isinstance(event, BoxesRemoved):
        world.remove_boxes(len(world.box_positions) if event.all else event.count or 0)
    elif isinstance(event, WallAppears):
        world.add_boxes(wall_boxes(event, config.box_size))
    elif isinstance(event, RobotsLeave):
        keep = everyone[: max(1, world.n_robots - event.count)]
        world.resize_swarm(np.array(keep), np.zeros((0, 3)), _robots(config, len(keep)))
        return keep, 0
    elif isinstance(event, RobotsJoin):
        poses = _free_poses(world, event.count, rng)
        world.resize_swarm(np.array(everyone), poses, _robots(config, world.n_robots + event.count))
        return everyone, event.count
    else:  # pragma: no cover - the union is closed
        raise AssertionError(f"unknown event {describe(event)}")
    return everyone, 0


def _robots(config: WorldConfig, count: int) -> WorldConfig:
    # A fixed start names one pose per robot: the changed swarm started at random instead.
    start = "random" if config.start == "fixed" else config.start
    return msgspec.structs.replace(config, robots=count, start=start, start_poses=[])


def _centres(world: World) -> np.ndarray:
    pose, offset = world.poses, world.config.body_offset
    return np.stack(
        [pose[:, 0] + offset * np.cos(pose[:, 2]), pose[:, 1] + offset * np.sin(pose[:, 2])],
        axis=1,
    )


def _free_boxes(
    world: World,
    count: int,
    region: tuple[float, float, float, float] | None,
    rng: np.random.Generator,
) -> np.ndarray:
    config = world.config
    rb = config.box_size / 2
    hw, hh = config.carpet_width / 2, config.carpet_height / 2
    x0, y0, x1, y1 = region or (-hw, -hh, hw, hh)
    robots, away = _centres(world), body_reach(config) + rb + 0.005
    taken = [tuple(p) for p in world.box_positions]
    out: list[tuple[float, float]] = []
    for _ in range(_TRIES * count):
        if len(out) == count:
            break
        x, y = rng.uniform(x0 + rb, x1 - rb), rng.uniform(y0 + rb, y1 - rb)
        if np.any(np.hypot(robots[:, 0] - x, robots[:, 1] - y) < away):
            continue
        if any(math.hypot(bx - x, by - y) < config.box_size + 0.001 for bx, by in taken):
            continue
        taken.append((x, y))
        out.append((x, y))
    if len(out) < count:
        raise ValueError(f"no room for {count} more boxes: {len(out)} found a place")
    return np.array(out).reshape(-1, 2)


def _free_poses(world: World, count: int, rng: np.random.Generator) -> np.ndarray:
    config = world.config
    reach = body_reach(config)
    hw, hh = config.carpet_width / 2 - reach, config.carpet_height / 2 - reach
    centres = [tuple(c) for c in _centres(world)]
    out: list[tuple[float, float, float]] = []
    for _ in range(_TRIES * count):
        if len(out) == count:
            break
        x, y, heading = rng.uniform(-hw, hw), rng.uniform(-hh, hh), rng.uniform(-math.pi, math.pi)
        if any(math.hypot(cx - x, cy - y) < 2 * reach + 0.01 for cx, cy in centres):
            continue
        centres.append((x, y))
        out.append((x, y, heading))
    if len(out) < count:
        raise ValueError(f"no room for {count} more robots: {len(out)} found a place")
    return np.array(out).reshape(-1, 3)
