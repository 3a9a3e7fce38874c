"""An experiment's events: refused by key when they cannot happen, and each kind changes the
simulated world as docs/changing-arenas.md says."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from master_service.experiments.simulate import simulation_experiment
from minimize_surprise.config import decode_experiment
from minimize_surprise.errors import ConfigError
from minimize_surprise.events import (
    BoxesAdded,
    BoxesRemoved,
    LightMoves,
    RobotsJoin,
    RobotsLeave,
    WallAppears,
)
from minimize_surprise.network import spec_from_config
from simulator.engine import Swarm
from simulator.events import apply_to_world, check_arena_events, event_rng, wall_boxes
from simulator.experiment import simulated_safety, world_config


def experiment(scenario: str = "gradient", events: list | None = None, evaluations: int = 20):
    return simulation_experiment(
        data={
            "setting": "paper",
            "scenario": scenario,
            "robots": 4,
            "seed": 2,
            "evolution": {"evaluations": evaluations},
            "evaluation_steps": 20,
            "events": events or [],
        }
    )


@pytest.mark.parametrize(
    ("event", "key", "words"),
    [
        ({"kind": "lamp-falls", "evaluation": 3}, "events[0]", "kind"),
        ({"kind": "light-moves", "evaluation": 30, "position": [0, 0]}, "events[0].evaluation",
         "beyond the run's 20"),
        ({"kind": "light-moves", "position": [0, 0]}, "events[0]", "either `evaluation`"),
        ({"kind": "light-moves", "evaluation": 2, "seconds": 5, "position": [0, 0]}, "events[0]",
         "not both"),
        ({"kind": "boxes-removed", "evaluation": 2}, "events[0].count", "`all: true`"),
        ({"kind": "wall-appears", "evaluation": 2, "start": [0, 0], "end": [0.1, 0.1]},
         "events[0].end", "horizontally or vertically"),
        ({"kind": "robots-leave", "evaluation": 2, "count": 4}, "events[0].count",
         "the swarm would have 0"),
        ({"kind": "boxes-added", "evaluation": 2, "count": 0}, "events[0].count", ">= 1"),
    ],
)  # fmt: skip
def test_a_malformed_event_is_refused_by_its_key(event, key, words):
    data = {"robots": 4, "evolution": {"evaluations": 20}, "events": [event]}
    with pytest.raises(ConfigError) as info:
        decode_experiment(data, file="exp.yaml")
    assert info.value.key is not None and info.value.key.startswith(key)
    assert words in str(info.value) and "exp.yaml" in str(info.value)


@pytest.mark.parametrize(
    ("scenario", "event", "key", "words"),
    [
        ("gradient", LightMoves(evaluation=2, position=(0.9, 0.0)), "events[0].position",
         "outside the 1.1 x 1.1 m floor"),
        ("basic", LightMoves(evaluation=2, position=(0.1, 0.0)), "events[0].kind",
         "arena with a lamp"),
        ("basic", BoxesRemoved(evaluation=2, count=1), "events[0].count", "has 0 then"),
        ("boxes", WallAppears(evaluation=2, start=(0.0, -0.2), end=(0.0, 0.9)), "events[0].end",
         "outside"),
        ("boxes", BoxesAdded(evaluation=2, count=3, region=(0.2, 0.2, 0.1, 0.3)),
         "events[0].region", "x0 < x1"),
    ],
)  # fmt: skip
def test_an_event_the_arena_cannot_hold_is_refused_by_its_key(scenario, event, key, words):
    config = world_config(experiment(scenario))
    with pytest.raises(ConfigError) as info:
        check_arena_events([event], config, file="exp.yaml")
    assert info.value.key == key and words in str(info.value)


def test_removing_more_boxes_than_were_added_counts_the_events_before():
    config = world_config(experiment("basic"))
    added = BoxesAdded(evaluation=2, count=3)
    check_arena_events([added, BoxesRemoved(evaluation=3, count=3)], config)
    with pytest.raises(ConfigError, match="has 3 then") as info:
        check_arena_events([BoxesRemoved(evaluation=3, count=4), added], config)
    assert info.value.key == "events[0].count"


def swarm(scenario: str = "gradient") -> Swarm:
    exp = experiment(scenario)
    return Swarm(world_config(exp), simulated_safety(exp), spec_from_config(exp), exp.seed)


def test_the_light_moves_and_the_light_sensors_read_the_new_gradient():
    world = swarm().world
    world.set_pose(0, 0.3, 0.3, 0.0)
    light = [world.sensors.index("light.0"), world.sensors.index("light.1")]
    far = world.sensor_matrix()[0, light].copy()
    before = world.light_at(0.3, 0.3)
    apply_to_world(world, LightMoves(evaluation=2, position=(0.3, 0.3)), event_rng(0, 0))
    assert world.config.light_position == (0.3, 0.3)
    assert world.light_at(0.3, 0.3) == pytest.approx(world.config.light_centre)
    assert world.light_at(0.3, 0.3) > before
    # The kernels see it: the robot now under the lamp reads more light than before.
    assert (world.sensor_matrix()[0, light] > far + 0.1).all()


def test_boxes_are_added_clear_of_robots_and_removed_last_first():
    world = swarm("boxes").world
    count = len(world.box_positions)
    apply_to_world(world, BoxesAdded(evaluation=2, count=7), event_rng(0, 1))
    assert len(world.box_positions) == count + 7
    added = world.box_positions[count:].copy()
    # Repeatable: the event's generator is seeded.
    again = swarm("boxes").world
    apply_to_world(again, BoxesAdded(evaluation=2, count=7), event_rng(0, 1))
    assert np.array_equal(again.box_positions[count:], added)
    apply_to_world(world, BoxesRemoved(evaluation=3, count=7), event_rng(0, 2))
    assert len(world.box_positions) == count
    apply_to_world(world, BoxesRemoved(evaluation=4, all=True), event_rng(0, 3))
    assert len(world.box_positions) == 0
    s = swarm("boxes")
    s.world.remove_boxes(len(s.world.box_positions))
    s.evaluate(np.zeros(s.layout.size), 5)  # the engine steps a world without boxes


def test_a_wall_is_a_line_of_boxes_a_robot_pushes_ahead():
    s = swarm("basic")
    world = s.world
    wall = WallAppears(evaluation=2, start=(-0.3, 0.2), end=(0.3, 0.2))
    apply_to_world(world, wall, event_rng(0, 0))
    boxes = world.box_positions
    assert len(boxes) == len(wall_boxes(wall, world.config.box_size)) == 23
    assert np.allclose(boxes[:, 1], 0.2) and boxes[:, 0].min() > -0.3
    # Every robot but one far away; the one drives straight at the wall from below.
    for i in range(1, world.n_robots):
        world.set_pose(i, -0.4 + 0.2 * i, -0.4, 0.0)
    world.set_pose(0, 0.0, 0.0, np.pi / 2)
    world.set_commands(np.array([[1.0, 1.0]] + [[0.0, 0.0]] * (world.n_robots - 1)))
    for _ in range(300):
        world.step()
    # It reached the wall and pushed its boxes ahead; none passed through its body.
    assert world.poses[0, 1] > 0.15
    near = np.abs(world.box_positions[:, 0]) < 0.03
    assert (world.box_positions[near, 1] > 0.21).all()
    assert (world.box_positions[near, 1] > world.poses[0, 1]).all()
    far = np.abs(world.box_positions[:, 0]) > 0.15
    assert np.allclose(world.box_positions[far, 1], 0.2, atol=1e-3)


def test_robots_leave_and_join_the_engines_swarm():
    s = swarm("basic")
    keep, joined = apply_to_world(s.world, RobotsLeave(evaluation=2, count=2), event_rng(0, 0))
    left, new = s.resize(keep, joined)
    assert left == ["sim-2", "sim-3"] and new == [] and s.ids == ["sim-0", "sim-1"]
    assert s.world.n_robots == 2 and s.safety.shape == (2, 5)
    assert len(s.evaluate(np.zeros(s.layout.size), 5).fitness) == 2
    keep, joined = apply_to_world(s.world, RobotsJoin(evaluation=3, count=3), event_rng(0, 1))
    left, new = s.resize(keep, joined)
    # A robot that joins never takes the id of one that left.
    assert left == [] and new == ["sim-4", "sim-5", "sim-6"]
    assert s.world.n_robots == 5 and len(s.evaluate(np.zeros(s.layout.size), 5).fitness) == 5
    centres = s.world.poses[:, :2]
    gaps = np.hypot(*(centres[:, None] - centres[None]).transpose(2, 0, 1))
    assert gaps[np.triu_indices(5, 1)].min() > 0.1


def test_an_experiment_without_events_has_none():
    assert experiment().events == []
    with_events = msgspec.structs.replace(experiment(), events=[])
    assert with_events == experiment()
