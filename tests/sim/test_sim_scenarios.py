"""Named scenarios and their overrides (simulator.scenarios)."""

from __future__ import annotations

import pytest

from minimize_surprise.errors import ConfigError
from minimize_surprise.sensors import FORCE_SENSORS, GROUND_SENSORS, IR_SENSORS, LIGHT_SENSORS
from simulator.scenarios import SCENARIOS, WorldConfig, scenario_config
from simulator.world import TooManyRobotsError, World


def test_the_three_scenarios_are_named():
    assert SCENARIOS == ("basic", "boxes", "gradient")


def test_basic_is_ten_robots_on_a_metre_with_ir_and_ground():
    cfg = scenario_config("basic")
    assert (cfg.robots, cfg.arena_side, cfg.start) == (10, 1.0, "random")
    assert cfg.sensors == IR_SENSORS + GROUND_SENSORS
    assert not cfg.boxes and not cfg.light and not cfg.walls_visible_to_ir
    assert cfg.max_speed == pytest.approx(0.106) and cfg.dt == pytest.approx(0.1)


def test_boxes_is_four_robots_from_the_centre_with_force():
    cfg = scenario_config("boxes")
    assert (cfg.robots, cfg.arena_side, cfg.start) == (4, 1.1, "centre")
    assert cfg.boxes and cfg.has_blade and not cfg.light
    assert cfg.sensors == IR_SENSORS + GROUND_SENSORS + FORCE_SENSORS
    # About 14 % of 1.21 m^2 covered by 2.5 cm boxes: 220 per square metre.
    assert cfg.box_count == 271


def test_gradient_is_boxes_plus_the_light():
    cfg = scenario_config("gradient")
    assert cfg.light and cfg.boxes and cfg.robots == 4
    assert cfg.sensors == IR_SENSORS + GROUND_SENSORS + FORCE_SENSORS + LIGHT_SENSORS


def test_overrides_replace_the_scenario_defaults():
    cfg = scenario_config("boxes", {"arena_side": 0.8, "robots": 2, "noise": 0.01})
    assert (cfg.arena_side, cfg.robots, cfg.noise) == (0.8, 2, 0.01)
    assert cfg.boxes  # untouched defaults stay
    assert isinstance(cfg, WorldConfig)


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        ({"arena_side": "big"}, "simulation.arena_side"),
        ({"arena_side": -1.0}, "simulation.arena_side"),
        ({"robots": 0}, "simulation.robots"),
        ({"start": "corner"}, "simulation.start"),
        ({"colour": "red"}, "simulation.colour"),
        ({"sensors": ["ir.f0", "sonar"]}, "simulation.sensors"),
        ({"sensors": ["ir.f0", "ir.f0"]}, "simulation.sensors"),
        ({"light": True, "light_corner": 1.0}, "simulation.light_corner"),
        ({"box_coverage": 0.9}, "simulation.box_coverage"),
    ],
)
def test_a_bad_override_names_its_key(overrides, key):
    with pytest.raises(ConfigError) as caught:
        scenario_config("basic", overrides, file="exp.yaml")
    assert caught.value.key == key
    assert "exp.yaml" in str(caught.value) and key in str(caught.value)


def test_an_unknown_scenario_is_a_config_error():
    with pytest.raises(ConfigError) as caught:
        scenario_config("maze")
    assert caught.value.key == "scenario"
    assert "basic" in caught.value.reason


def test_overrides_must_be_a_mapping():
    with pytest.raises(ConfigError) as caught:
        scenario_config("basic", ["arena_side"])  # type: ignore[arg-type]
    assert caught.value.key == "simulation"


def test_too_many_robots_for_the_arena_is_a_config_error():
    with pytest.raises(TooManyRobotsError) as caught:
        World(scenario_config("basic", {"robots": 60, "arena_side": 0.5}), seed=0)
    assert caught.value.key == "simulation.robots"
    assert isinstance(caught.value, ConfigError)
    # As many as the random start found room for do start.
    fit = caught.value.fit
    assert 1 <= fit < 60 and caught.value.approximate
    assert (
        World(scenario_config("basic", {"robots": fit, "arena_side": 0.5}), seed=0).n_robots == fit
    )
    with pytest.raises(TooManyRobotsError) as caught:
        World(scenario_config("boxes", {"robots": 12, "arena_side": 0.5}), seed=0)
    assert caught.value.key == "simulation.robots"
    assert "around the centre of a 0.5 m carpet" in caught.value.reason
    fit = caught.value.fit
    assert (
        World(scenario_config("boxes", {"robots": fit, "arena_side": 0.5}), seed=0).n_robots == fit
    )
    with pytest.raises(TooManyRobotsError, match="around the centre"):
        World(scenario_config("boxes", {"robots": fit + 1, "arena_side": 0.5}), seed=0)
