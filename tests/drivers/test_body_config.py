"""BodyConfig and its parts decode from plain data; mistakes name the key."""

from __future__ import annotations

import pytest

from drivers.config import BodyConfig, ThymioConfig
from minimize_surprise.config import decode
from minimize_surprise.errors import ConfigError
from minimize_surprise.sensors import ALL_SENSORS, GROUND_SENSORS, IR_SENSORS


def test_defaults_are_a_bare_thymio():
    config = decode({}, BodyConfig)
    assert config.thymio == ThymioConfig()
    assert config.thymio.speed_scale == 265 and config.thymio.max_target == 500
    assert config.thymio.timeout == 0.25 and config.thymio.node == "thymio-II"
    assert config.sensor_names() == IR_SENSORS + GROUND_SENSORS


def test_full_robot():
    config = decode(
        {
            "thymio": {"bus": "system", "speed_scale": 300, "failsafe": True},
            "light": [{"mux": {"channel": 0}}, {"mux": {"channel": 1}, "integration_ms": 400}],
            "force": {"address": 0x49, "inputs": "AIN2-AIN3", "data_rate": 860},
        },
        BodyConfig,
    )
    assert config.sensor_names() == ALL_SENSORS
    assert config.light[0].mux is not None and config.light[0].mux.address == 0x70
    assert config.force is not None and config.force.pga_range_volts == 0.256


@pytest.mark.parametrize(
    ("data", "key", "reason"),
    [
        ({"thymio": {"bus": "sesion"}}, "thymio.bus", "expected 'session', 'system'"),
        ({"thymio": {"ground": "prox.ground.ambiant"}}, "thymio.ground", "Invalid enum"),
        ({"thymio": {"max_target": 600}}, "thymio.max_target", "<= 500"),
        ({"thymio": {"speeed_scale": 300}}, "thymio.speeed_scale", "unknown key"),
        ({"light": [{}, {"bus": 3}, {"bus": 4}]}, "light", "at most 2"),
        ({"light": [{}, {}]}, "light[1]", "same bus"),
        ({"light": [{"mux": {"channel": 8}}]}, "light[0].mux.channel", "<= 7"),
        ({"light": [{"integration_ms": 300}]}, "light[0].integration_ms", "Invalid enum"),
        ({"force": {"pga_range_volts": 0.3}}, "force.pga_range_volts", "expected one of"),
        ({"force": {"full_scale_volts": 0.5}}, "force.full_scale_volts", "exceeds the ADC range"),
        ({"force": {"address": 0x29}}, "force.address", ">= 72"),
    ],
)
def test_mistakes_name_the_key(data: dict, key: str, reason: str):
    with pytest.raises(ConfigError) as info:
        decode(data, BodyConfig, file="robot.yaml")
    assert info.value.key == key
    assert reason in info.value.reason
    assert info.value.file == "robot.yaml"
