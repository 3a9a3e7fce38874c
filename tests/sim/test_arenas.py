"""Arena files: every shipped one loads and simulates, a bad one is refused by file and key, a
rectangular floor, fixed starts, box regions and a moved lamp behave as a person expects."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from master_service.experiments.simulation_setup import simulation_experiment, world_config
from minimize_surprise.config import load_experiment
from minimize_surprise.errors import ConfigError
from simulator.arenas import load_arena, shipped_arenas
from simulator.scenarios import scenario_config
from simulator.world import World

EXAMPLES = Path(__file__).resolve().parents[2] / "deploy" / "examples"


def test_the_shipped_arenas_are_the_papers() -> None:
    assert shipped_arenas() == ("basic", "boxes", "gradient", "real-objects")
    for name in shipped_arenas():
        arena = load_arena(name)
        assert arena.name == name and arena.description


def test_the_real_arena_is_the_papers_real_one() -> None:
    config = scenario_config("boxes", arena=load_arena("real-objects"))
    assert (config.carpet_width, config.carpet_height) == (2.2, 2.9)
    assert config.ground_outside > 0.55 > config.ground_carpet  # the rim reads bright
    assert config.walls_visible_to_ir and config.wall_margin > 0
    # About 220 boxes of 2.5 cm per square metre, 14 % of the floor.
    assert config.box_count / (2.2 * 2.9) == pytest.approx(220, rel=0.02)
    world = World(config, seed=3)
    assert len(world.box_positions) == config.box_count
    assert np.allclose(world.poses[:, :2], [[0.2, 0.2], [-0.2, 0.2], [-0.2, -0.2], [0.2, -0.2]])
    assert np.allclose(world.poses[:, 2], np.radians([45, 135, -135, -45]))
    # Fixed starts: the same poses for every seed, the boxes differ.
    other = World(config, seed=4)
    assert np.array_equal(other.poses, world.poses)
    assert not np.array_equal(other.box_positions, world.box_positions)


def test_a_rectangular_floor_keeps_robots_and_boxes_in_it() -> None:
    config = scenario_config("boxes", arena=load_arena("real-objects"))
    world = World(config, seed=1)
    boxes = world.box_positions
    assert np.all(np.abs(boxes[:, 0]) <= 1.1) and np.all(np.abs(boxes[:, 1]) <= 1.45)
    assert np.abs(boxes[:, 1]).max() > 1.2  # the boxes use the floor's whole height
    # Robots driven straight along y stop at the walls 1.45 + 0.15 m out, not at the side's.
    world.set_pose(0, 0.0, 0.0, math.pi / 2)
    world.set_box_positions(np.zeros((0, 2)))
    for _ in range(400):
        world.set_command(0, 1.0, 1.0)
        world.step()
    assert 1.3 < world.poses[0, 1] < config.wall_hy
    ground = world.sensor_values(0)[list(config.sensors).index("ground.0")]
    assert ground == config.ground_outside  # it sees the rim beyond the floor's edge


def test_the_experiment_names_its_arena_by_name_or_path(tmp_path: Path) -> None:
    own = tmp_path / "arenas" / "lab-floor.yaml"
    own.parent.mkdir()
    own.write_text(
        "name: lab-floor\nfloor: {width: 1.5, height: 0.9}\n"
        "start: {kind: random, region: [-0.7, -0.4, 0.0, 0.4]}\n"
    )
    experiment = tmp_path / "experiment.yaml"
    experiment.write_text("setting: lab\narena: arenas/lab-floor.yaml\nrobots: 3\n")
    loaded = load_experiment(experiment)
    assert loaded.arena == str(own.resolve()) and loaded.arena_name == "lab-floor"
    config = world_config(simulation_experiment(config_file=experiment))
    assert (config.carpet_width, config.carpet_height) == (1.5, 0.9)
    world = World(config, seed=2)
    assert np.all(world.poses[:, 0] < 0.0)  # every robot in the left half, its region


def test_the_object_manipulation_example_runs_in_its_arena() -> None:
    experiment = simulation_experiment(config_file=EXAMPLES / "experiment-object-manipulation.yaml")
    assert experiment.arena == "real-objects" and experiment.setting == "lab"
    assert experiment.evolution.evaluations == 350 and experiment.robots == 4
    assert experiment.evaluation_steps == 100 and experiment.step_period == 0.1
    assert "force" in experiment.sensors
    config = world_config(experiment)
    assert (config.carpet_width, config.carpet_height) == (2.2, 2.9)


def test_the_lab_setting_runs_the_papers_real_robot_evaluations() -> None:
    assert simulation_experiment("basic", setting="lab").evolution.evaluations == 350
    assert simulation_experiment("basic", setting="paper").evolution.evaluations == 1000


def test_a_lamp_off_the_centre_is_brightest_under_it() -> None:
    config = scenario_config("gradient", {"light_position": [0.3, -0.2]})
    world = World(config)
    assert world.light_at(0.3, -0.2) == pytest.approx(config.light_centre)
    assert world.light_at(0.3, -0.2) > world.light_at(0.0, 0.0)


BAD = [
    ("floor: {width: 0}", "floor.width", "Expected `float` > 0.0"),
    ("floor: {width: 1.0, height: -2}", "floor.height", "> 0.0"),
    ("floor: {width: 1.0}\nwalls: {margin: -0.1}", "walls.margin", ">= 0.0"),
    ("floor: {width: 1.0}\nwals: {margin: 0.1}", "wals", "unknown key"),
    ("floor: {width: 1.0, colour: red}", "floor.colour", "unknown key"),
    (
        "floor: {width: 1.0}\nstart: {kind: fixed, poses: [[0.7, 0, 0]]}",
        "start.poses",
        "outside the 1 x 1 m floor",
    ),
    (
        "floor: {width: 1.0}\nstart: {kind: fixed, poses: [[0.45, 0, 0]]}",
        "start.poses",
        "reaches beyond the 1 x 1 m floor",
    ),
    (
        "floor: {width: 1.0}\nstart: {kind: random, region: [-0.2, 0, 0.9, 0.4]}",
        "start.region",
        "reaches beyond",
    ),
    ("floor: {width: 1.0}\nboxes: {count: 1000, size: 0.025}", "boxes.count", "do not fit"),
    ("floor: {width: 1.0}\nboxes: {count: 10, coverage: 0.1}", "boxes.count", "not both"),
    ("floor: {width: 0.02}\nboxes: {size: 0.025}", "boxes.size", "not smaller"),
    ("floor: {width: 1.0}\nstart: {kind: ring, poses: [[0, 0, 0]]}", "start.poses", "only"),
]


@pytest.mark.parametrize(("body", "key", "reason"), BAD)
def test_a_bad_arena_file_is_refused_by_file_and_key(
    tmp_path: Path, body: str, key: str, reason: str
) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(f"name: bad\n{body}\n")
    with pytest.raises(ConfigError) as info:
        load_arena(path)
    assert info.value.key == key and info.value.file == str(path)
    assert reason in str(info.value)


def test_overlapping_start_poses_are_refused_by_file_and_key(tmp_path: Path) -> None:
    path = tmp_path / "crowded.yaml"
    path.write_text(
        "name: crowded\nfloor: {width: 1.0}\n"
        "start: {kind: fixed, poses: [[0, 0, 0], [0.1, 0, 0]]}\n"
    )
    with pytest.raises(ConfigError, match="poses 1 and 2 overlap") as info:
        load_arena(path)
    assert info.value.key == "start.poses" and info.value.file == str(path)
    # The same rule where an experiment gives the poses itself.
    with pytest.raises(ConfigError, match="poses 1 and 2 overlap") as info:
        World(
            scenario_config(
                "basic", {"robots": 2, "start": "fixed", "start_poses": [[0, 0, 0], [0.1, 0, 0]]}
            )
        )
    assert info.value.key == "simulation.start_poses"


def test_the_arena_files_body_is_the_simulators() -> None:
    from simulator.arenas import BODY_OFFSET, BODY_RADIUS
    from simulator.scenarios import WorldConfig

    assert (WorldConfig().robot_radius, WorldConfig().body_offset) == (BODY_RADIUS, BODY_OFFSET)


def test_fixed_poses_must_match_the_robots(tmp_path: Path) -> None:
    experiment = tmp_path / "experiment.yaml"
    experiment.write_text("setting: lab\nscenario: boxes\narena: real-objects\nrobots: 5\n")
    with pytest.raises(ConfigError, match="4 poses for 5 robots") as info:
        world_config(simulation_experiment(config_file=experiment))
    assert info.value.key == "simulation.start_poses"


def test_an_unknown_arena_names_the_shipped_ones(tmp_path: Path) -> None:
    experiment = tmp_path / "experiment.yaml"
    experiment.write_text("setting: lab\narena: real-object\n")
    with pytest.raises(ConfigError, match=r"unknown arena 'real-object'.*real-objects") as info:
        simulation_experiment(config_file=experiment)
    assert info.value.key == "arena" and info.value.file == str(experiment)
    experiment.write_text("setting: lab\narena: missing/arena.yaml\n")
    with pytest.raises(ConfigError, match="does not exist"):
        simulation_experiment(config_file=experiment)


def test_the_playground_world_is_built_from_the_arena() -> None:
    import re
    import struct

    from standins.playground_world import BEYOND_WALLS, WALL_THICKNESS, Arena

    config = scenario_config("basic", {"robots": 4}, arena=load_arena("real-objects"))
    world = Arena.of(config, seed=1)
    xml = world.world_xml([7001, 7002, 7003, 7004], "ground.png")
    beyond = 2 * (0.15 + WALL_THICKNESS + BEYOND_WALLS)
    size = re.search(r'<world w="([\d.]+)" h="([\d.]+)"', xml)
    assert size and float(size[1]) == pytest.approx((2.2 + beyond) * 100, abs=0.01)
    assert float(size[2]) == pytest.approx((2.9 + beyond) * 100, abs=0.01)
    boxes = re.findall(r'<wall [^>]*color="box" mass="10"/>', xml)
    assert len(boxes) == config.box_count == len(World(config, 1).box_positions)
    assert len(re.findall(r'color="wall"/>', xml)) == 4
    robots = re.findall(r'<robot type="thymio2" x="([\d.]+)" y="([\d.]+)"', xml)
    centre = (float(size[1]) / 2, float(size[2]) / 2)
    offsets = np.array([(float(x) - centre[0], float(y) - centre[1]) for x, y in robots])
    assert np.allclose(offsets, [(20, 20), (-20, 20), (-20, -20), (20, -20)], atol=0.01)
    png = world.ground_png()
    width, height = struct.unpack(">II", png[16:24])
    assert (width, height) == (math.ceil((2.2 + beyond) * 100), math.ceil((2.9 + beyond) * 100))
