"""The fleet's inventory: decoding, one error per mistake naming the file and the key, and the
master admitting the inventory's swarm (docs/fleet.md)."""

from __future__ import annotations

from pathlib import Path

import pytest
from master_helpers import SECRET, master_config

from master_service import Master
from master_service.config import inventory_of, load_master_config
from master_service.inventory import Calibration, load_inventory
from minimize_surprise.errors import ConfigError
from minimize_surprise.wire import REFUSED_UNKNOWN_ROBOT
from standins.scripted_robots import RobotRefusedError, ScriptedRobot

FLEET = """\
robots:
  - {name: r0, address: r0.local, marker: 10}
  - {name: r1, address: 192.0.2.11, node: thymio-7, marker: 11,
     calibration: {ground_floor: [0.62, 0.6], ground_rim: [0.1, 0.12], wheel_right: 0.97}}
  - {name: r2, address: "2001:db8::2", marker: 12}
  - {name: r3, address: r3.local, enabled: false}
  - {name: r4, address: r4.local, marker: 14, spare: true}
"""


def write(directory: Path, text: str, name: str) -> Path:
    path = directory / name
    path.write_text(text)
    return path


def test_an_inventory_lists_swarm_spares_markers_and_calibration(tmp_path):
    fleet = load_inventory(write(tmp_path, FLEET, "fleet.yaml"))
    assert fleet.swarm == ["r0", "r1", "r2"]
    assert fleet.spares == ["r4"]
    assert fleet.enabled == ["r0", "r1", "r2", "r4"]
    assert fleet.markers() == {"r0": 10, "r1": 11, "r2": 12, "r4": 14}
    r1 = fleet.robot("r1")
    assert r1 is not None and r1.node == "thymio-7" and r1.address == "192.0.2.11"
    assert r1.calibration == Calibration(
        ground_floor=(0.62, 0.6), ground_rim=(0.1, 0.12), wheel_left=1.0, wheel_right=0.97
    )
    r0 = fleet.robot("r0")
    assert r0 is not None and r0.node == "thymio-II" and r0.calibration is None
    assert fleet.robot("nobody") is None


@pytest.mark.parametrize(
    "text, key, words",
    [
        (
            "robots:\n  - {name: a, address: a}\n  - {name: a, address: b}\n",
            "robots[1].name",
            "'a' is listed twice (also robots[0])",
        ),
        (
            "robots:\n  - {name: a, address: a, marker: 3}\n"
            "  - {name: b, address: b, marker: 3, enabled: false}\n",
            "robots[1].marker",
            "marker 3 is already a's",
        ),
        (
            "robots:\n  - {name: a, address: a}\n"
            "  - {name: b, address: b, spare: true, enabled: false}\n",
            "robots[1].spare",
            "a spare but not enabled",
        ),
        ("robots:\n  - {name: a}\n", "robots[0].address", "required key is missing"),
        ("robots:\n  - {name: 'no spaces', address: a}\n", "robots[0].name", "matching regex"),
        ("robots:\n  - {name: a, address: 'pi@a:22 x'}\n", "robots[0].address", "matching regex"),
        ("robots:\n  - {name: a, address: a, marker: -1}\n", "robots[0].marker", ">= 0"),
        ("robots:\n  - {name: a, address: a, colour: red}\n", "robots[0].colour", "unknown key"),
        (
            "robots:\n  - {name: a, address: a, calibration: {ground_floor: [0.5, 1.5]}}\n",
            "robots[0].calibration.ground_floor[1]",
            "<= 1.0",
        ),
        (
            "robots:\n  - {name: a, address: a, calibration: {wheel_left: 0}}\n",
            "robots[0].calibration.wheel_left",
            "> 0.0",
        ),
        ("robots: []\n", "robots", "lists no robot"),
    ],
)
def test_each_mistake_is_named_by_file_and_key(tmp_path, text, key, words):
    path = write(tmp_path, text, "fleet.yaml")
    with pytest.raises(ConfigError) as info:
        load_inventory(path)
    assert info.value.file == str(path)
    assert info.value.key == key
    assert words in info.value.reason


@pytest.fixture
def lab(tmp_path: Path) -> Path:
    write(tmp_path, "robots: 3\n", "experiment.yaml")
    write(tmp_path, "s3cret\n", "secret.txt")
    write(tmp_path, FLEET, "fleet.yaml")
    return tmp_path


def test_the_master_file_takes_its_robots_from_the_inventory(lab):
    path = write(
        lab, "experiment_file: experiment.yaml\nsecret_file: secret.txt\ninventory: fleet.yaml\n",
        "master.yaml",
    )  # fmt: skip
    config = load_master_config(path)
    assert config.inventory == str(lab / "fleet.yaml")
    assert config.allowed_robots == ["r0", "r1", "r2"]  # neither the disabled nor the spare
    fleet = inventory_of(config)
    assert fleet is not None and fleet.spares == ["r4"]


def test_allowed_robots_that_agree_with_the_inventory_are_fine(lab):
    path = write(
        lab,
        "experiment_file: experiment.yaml\ninventory: fleet.yaml\nallowed_robots: [r2, r1, r0]\n",
        "master.yaml",
    )
    assert load_master_config(path).allowed_robots == ["r2", "r1", "r0"]


def test_allowed_robots_that_disagree_with_the_inventory_are_an_error(lab):
    path = write(
        lab,
        "experiment_file: experiment.yaml\ninventory: fleet.yaml\nallowed_robots: [r0, r1, r4]\n",
        "master.yaml",
    )
    with pytest.raises(ConfigError) as info:
        load_master_config(path)
    assert info.value.file == str(path) and info.value.key == "allowed_robots"
    assert "r4 not in its swarm" in info.value.reason and "r2 of its swarm not listed" in (
        info.value.reason
    )


def test_a_missing_or_bad_inventory_is_named(lab):
    path = write(lab, "experiment_file: experiment.yaml\ninventory: nowhere.yaml\n", "master.yaml")
    with pytest.raises(ConfigError) as info:
        load_master_config(path)
    assert info.value.key == "inventory" and "nowhere.yaml does not exist" in info.value.reason
    write(lab, "robots:\n  - {name: a, address: a}\n  - {name: a, address: b}\n", "bad.yaml")
    path = write(lab, "experiment_file: experiment.yaml\ninventory: bad.yaml\n", "master.yaml")
    with pytest.raises(ConfigError) as info:
        load_master_config(path)
    assert info.value.file == str(lab / "bad.yaml") and info.value.key == "robots[1].name"


def test_a_swarm_larger_than_the_inventory_s_is_an_error(lab):
    write(lab, "robots: 4\n", "experiment.yaml")
    path = write(lab, "experiment_file: experiment.yaml\ninventory: fleet.yaml\n", "master.yaml")
    with pytest.raises(ConfigError, match="needs 4 robots"):
        load_master_config(path)


async def test_the_master_admits_the_inventory_s_swarm_only(lab, tmp_path):
    path = write(lab, "experiment_file: experiment.yaml\ninventory: fleet.yaml\n", "master.yaml")
    config = load_master_config(path)
    config = master_config(config.experiment, allowed_robots=config.allowed_robots)
    async with Master(config, tmp_path / "run", secret=SECRET) as master:
        for outsider in ("r3", "r4"):  # disabled; a spare
            with pytest.raises(RobotRefusedError) as info:
                await ScriptedRobot(outsider, SECRET, master.port).connect()
            assert info.value.code == REFUSED_UNKNOWN_ROBOT
        robot = ScriptedRobot("r1", SECRET, master.port)
        await robot.connect()
        assert master.connected_robots == ["r1"]
        await robot.close()


def test_the_tracker_takes_the_markers_from_the_inventory(lab, tmp_path):
    """``track --inventory FILE``, or the inventory the run's master file named; a tracking file
    that lists its own markers keeps them unless ``--inventory`` is given."""
    import argparse

    import yaml

    from master_service.cli_lab import _marker_inventory

    run = tmp_path / "run"
    run.mkdir()
    snapshot = {"experiment": {"robots": 3}, "inventory": str(lab / "fleet.yaml")}
    (run / "config.yaml").write_text(yaml.safe_dump(snapshot))
    every = {"r0": 10, "r1": 11, "r2": 12, "r4": 14}  # not the disabled r3 (it has none anyway)

    def markers(**given):
        args = argparse.Namespace(**{"inventory": None, "run": run, **given})
        return _marker_inventory(args, has_ids=given.pop("has_ids", False))

    assert markers() == every  # the run's
    assert markers(has_ids=True) is None  # the tracking file's own
    other = write(lab, "robots:\n  - {name: r0, address: a, marker: 30}\n", "other.yaml")
    assert markers(inventory=other, has_ids=True) == {"r0": 30}
    assert markers(run=None) is None
    # With a post-evaluation, only its robots: a spare's marker is not in the video.
    (run / "post_evaluation.json").write_text(
        '{"format": 1, "evaluation_id": 9, "steps": 4, "genome_fitness": null, '
        '"swarm_fitness": null, "robots": {"r0": {"fitness": 0.5, "stats": {"steps_run": 4, '
        '"overruns": 0, "interventions": {}}}}}'
    )
    assert markers() == {"r0": 10}
