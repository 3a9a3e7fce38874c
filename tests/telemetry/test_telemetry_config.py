"""The ``telemetry`` configuration section: broker URL, prefix, limits, and its place in the
agent's and the master's configuration files."""

from __future__ import annotations

import pytest

from master_service.config import load_master_config
from minimize_surprise.errors import ConfigError
from robot_agent.config import load_agent_config
from telemetry.config import (
    BrokerAddress,
    TelemetryConfig,
    check_prefix,
    parse_broker_url,
    require_client_library,
)


@pytest.mark.parametrize(
    "url, host, port",
    [
        ("mqtt://localhost", "localhost", 1883),
        ("mqtt://192.168.1.10:1884", "192.168.1.10", 1884),
        ("mqtt://[::1]:1999", "::1", 1999),
        ("mqtt://broker.lab/", "broker.lab", 1883),
    ],
)
def test_broker_urls_are_parsed(url, host, port):
    address = parse_broker_url(url)
    assert address == BrokerAddress(host, port)
    assert parse_broker_url(address.url) == address


@pytest.mark.parametrize(
    "url",
    [
        "localhost:1883",
        "http://localhost",
        "mqtt://",
        "mqtt://h:notaport",
        "mqtt://h:70000",
        "mqtt://h:0",
        "mqtt://user:pw@h",
        "mqtt://h/topic",
        "mqtts://h",
    ],
)
def test_bad_broker_urls_are_refused(url):
    with pytest.raises(ValueError):
        parse_broker_url(url)


@pytest.mark.parametrize("prefix", ["surprise", "lab-2/run_3", "a.b"])
def test_plain_prefixes_are_accepted(prefix):
    assert check_prefix(prefix) == prefix


@pytest.mark.parametrize("prefix", ["", "/surprise", "surprise/", "a//b", "a/+/b", "a/#", "$SYS"])
def test_prefixes_with_wildcards_or_empty_levels_are_refused(prefix):
    with pytest.raises(ValueError):
        check_prefix(prefix)


def test_defaults_are_off_without_a_broker():
    config = TelemetryConfig()
    assert not config.enabled
    assert (config.prefix, config.rate_hz, config.queue_size) == ("surprise", 2.0, 256)
    with pytest.raises(ValueError):
        _ = config.address


def _agent_file(tmp_path, telemetry: str) -> str:
    path = tmp_path / "agent.yaml"
    path.write_text(
        "robot_id: r1\nmaster: {host: 127.0.0.1, secret_file: s.key}\n" + telemetry,
        encoding="utf-8",
    )
    return str(path)


def test_the_agent_configuration_takes_a_telemetry_section(tmp_path):
    path = _agent_file(
        tmp_path,
        "telemetry:\n  broker: mqtt://10.0.0.5:1884\n  prefix: lab/a\n  rate_hz: 5\n"
        "  reconnect: {initial: 0.1, max: 2}\n",
    )
    config = load_agent_config(path)
    assert config.telemetry is not None and config.telemetry.enabled
    assert config.telemetry.address == BrokerAddress("10.0.0.5", 1884)
    assert config.telemetry.prefix == "lab/a" and config.telemetry.reconnect.max == 2
    assert load_agent_config(_agent_file(tmp_path, "")).telemetry is None


@pytest.mark.parametrize(
    "section, key",
    [
        ("telemetry: {broker: 'localhost:1883'}", "telemetry.broker"),
        ("telemetry: {broker: 'mqtt://h', prefix: 'a/#'}", "telemetry.prefix"),
        ("telemetry: {queue_size: 0}", "telemetry.queue_size"),
        ("telemetry: {rate_hz: -1}", "telemetry.rate_hz"),
        ("telemetry: {colour: blue}", "telemetry.colour"),
        ("telemetry: {reconnect: {initial: 5, max: 1}}", "telemetry.reconnect.max"),
    ],
)
def test_a_bad_telemetry_section_names_the_file_and_key(tmp_path, section, key):
    path = _agent_file(tmp_path, section + "\n")
    with pytest.raises(ConfigError) as info:
        load_agent_config(path)
    assert info.value.key == key and info.value.file == path


def test_the_master_configuration_keeps_telemetry_through_resolution(tmp_path):
    (tmp_path / "secret.txt").write_text("s3cret\n", encoding="utf-8")
    path = tmp_path / "master.yaml"
    path.write_text(
        "experiment: {robots: 2}\nsecret_file: secret.txt\n"
        "telemetry: {broker: 'mqtt://localhost', prefix: run-7}\n",
        encoding="utf-8",
    )
    config = load_master_config(path)
    assert config.telemetry == TelemetryConfig(broker="mqtt://localhost", prefix="run-7")


def test_a_configured_broker_without_the_mqtt_client_is_a_config_error(monkeypatch):
    require_client_library(None)
    require_client_library(TelemetryConfig())
    require_client_library(TelemetryConfig(broker="mqtt://h"))  # aiomqtt is installed here
    monkeypatch.setattr("importlib.util.find_spec", lambda name: None)
    require_client_library(TelemetryConfig())  # off: nothing is needed
    with pytest.raises(ConfigError) as info:
        require_client_library(TelemetryConfig(broker="mqtt://h"), file="agent.yaml")
    assert info.value.key == "telemetry.broker" and "pip install" in str(info.value)
