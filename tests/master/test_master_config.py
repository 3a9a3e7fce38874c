"""The master's configuration: resolution of files, one clear error per mistake, and a command
line that starts nothing when the configuration is bad."""

from __future__ import annotations

from pathlib import Path

import pytest
from master_helpers import SECRET, master_config

from master_service import Master
from master_service.cli import main
from master_service.config import (
    MasterConfig,
    build_ssl_context,
    load_master_config,
    load_secret,
)
from minimize_surprise.errors import ConfigError
from minimize_surprise.wire import DEFAULT_PORT
from transport.tls import ServerTlsConfig


def write(directory: Path, text: str, name: str = "master.yaml") -> Path:
    path = directory / name
    path.write_text(text)
    return path


@pytest.fixture
def lab(tmp_path):
    """A lab directory with an experiment file and a secret file."""
    write(tmp_path, "robots: 4\nevolution: {evaluations: 350}\n", "experiment.yaml")
    write(tmp_path, "s3cret\n", "secret.txt")
    return tmp_path


def test_a_file_resolves_experiment_and_paths(lab):
    path = write(
        lab,
        "experiment_file: experiment.yaml\nsecret_file: secret.txt\nhost: 0.0.0.0\n"
        "allowed_robots: [thymio-1, thymio-2, thymio-3, thymio-4, spare]\n",
    )
    config = load_master_config(path)
    assert config.experiment is not None and config.experiment.robots == 4
    assert config.experiment.evolution.evaluations == 350
    assert config.experiment_file is None
    assert config.secret_file == str(lab / "secret.txt")
    assert config.port == DEFAULT_PORT and config.robot_count == 4
    assert load_secret(config.secret_file) == b"s3cret"


def test_an_inline_experiment_and_defaults(lab):
    config = load_master_config(write(lab, "experiment: {robots: 2}\nexpected_robots: 1\n"))
    assert config.robot_count == 1 and config.host == "127.0.0.1"
    assert config.round_margin == 5.0 and config.heartbeat_interval == 2.0
    assert config.handshake_timeout == 10.0 and config.tls is None
    assert config.max_pending_connections == 64


@pytest.mark.parametrize(
    "text, key, words",
    [
        ("", "experiment", "exactly one of"),
        ("experiment: {}\nexperiment_file: experiment.yaml", "experiment", "exactly one of"),
        ("experiment: {}\nport: 70000", "port", "<= 65535"),
        ("experiment: {}\nprot: 1", "prot", "unknown key"),
        ("experiment: {}\nround_margin: 0", "round_margin", "> 0.0"),
        ("experiment: {}\nheartbeat_interval: soon", "heartbeat_interval", "float"),
        # The robots refuse intervals outside the protocol's bounds: so does the master.
        ("experiment: {}\nheartbeat_interval: 0.001", "heartbeat_interval", ">= 0.05"),
        ("experiment: {}\nheartbeat_interval: 600", "heartbeat_interval", "<= 60.0"),
        ("experiment: {}\nmax_pending_connections: 0", "max_pending_connections", ">= 1"),
        ("experiment: {}\nallowed_robots: ['a b']", "allowed_robots[0]", "matching regex"),
        ("experiment: {}\nallowed_robots: [a, a]", "allowed_robots", "listed twice"),
        ("experiment: {robots: 3}\nallowed_robots: [a, b]", "expected_robots", "lists only 2"),
        ("experiment_file: experiment.yaml\nexpected_robots: 5\nallowed_robots: [a]",
         "expected_robots", "lists only 1"),
        ("experiment: {robots: 0}", "experiment.robots", ">= 1"),
        ("experiment: {}\ntls: {cert_file: c.pem}", "tls.key_file", "missing"),
        ("experiment_file: nope.yaml", "experiment_file", "does not exist"),
        ("experiment: {}\nsecret_file: nope.txt", "secret_file", "does not exist"),
        ("experiment: {}\ntls: {cert_file: c.pem, key_file: k.pem}", "tls.cert_file", "exist"),
    ],
)  # fmt: skip
def test_bad_values_name_the_file_and_key(lab, text, key, words):
    path = write(lab, text)
    with pytest.raises(ConfigError) as info:
        load_master_config(path)
    assert info.value.file == str(path) and info.value.key == key, info.value
    assert words in str(info.value)


def test_an_error_in_the_experiment_file_names_that_file(lab):
    bad = write(lab, "evolution: {mutation_probability: 2}\n", "bad-experiment.yaml")
    with pytest.raises(ConfigError) as info:
        load_master_config(write(lab, f"experiment_file: {bad.name}\n"))
    assert info.value.file == str(bad) and info.value.key == "evolution.mutation_probability"


def test_secret_files(tmp_path):
    assert load_secret(write(tmp_path, "  abc \n\n", "s")) == b"abc"
    with pytest.raises(ConfigError, match="empty") as info:
        load_secret(write(tmp_path, "\n", "empty"))
    assert info.value.file == str(tmp_path / "empty")
    with pytest.raises(ConfigError, match="cannot read"):
        load_secret(tmp_path / "missing")


def test_a_bad_certificate_is_a_configuration_error(tmp_path):
    cert = write(tmp_path, "not a certificate", "cert.pem")
    with pytest.raises(ConfigError, match="certificate") as info:
        build_ssl_context(ServerTlsConfig(cert_file=str(cert), key_file=str(cert)))
    assert info.value.key == "tls.cert_file"


def test_config_structs_check_in_code_too():
    with pytest.raises(ValueError, match="exactly one"):
        MasterConfig()


# ---------------------------------------------------------------------------------------------
# The command line starts nothing with a bad configuration.


@pytest.mark.parametrize(
    "text, words",
    [
        ("experiment: {}\nport: -1", "key 'port'"),
        ("experiment: {}\n", "key 'secret_file': the robots' shared secret is needed"),
        ("experiment: {}\nsecret_file: empty.txt", "the secret file is empty"),
        ("experiment: {robots: [1]}\nsecret_file: secret.txt", "key 'experiment.robots'"),
    ],
)
def test_cli_run_with_bad_configuration_exits_2_with_one_message(lab, capsys, text, words):
    write(lab, "", "empty.txt")
    path = write(lab, text)
    out = lab / "out"
    assert main(["run", "--config", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err and err.startswith("surprise-master: ")
    assert not out.exists()


def test_cli_refuses_a_used_run_directory_and_a_non_run_directory(lab, capsys):
    path = write(lab, "experiment: {}\nsecret_file: secret.txt\n")
    used = lab / "used"
    used.mkdir()
    (used / "something").write_text("x")
    assert main(["run", "--config", str(path), "--out", str(used)]) == 2
    assert "resume" in capsys.readouterr().err
    for command in ("resume", "status", "report"):
        assert main([command, str(lab / "nowhere")]) == 2
        assert "is not a run directory" in capsys.readouterr().err


def test_cli_run_exits_1_when_the_port_is_busy(lab, capsys):
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        path = write(lab, f"experiment: {{}}\nsecret_file: secret.txt\nport: {port}\n")
        assert main(["run", "--config", str(path), "--out", str(lab / "run")]) == 1
    assert "address already in use" in capsys.readouterr().err.lower()
    assert not (lab / "run").exists()


async def test_a_frame_limit_too_small_for_the_genome_is_a_configuration_error(tmp_path):
    # Otherwise the master starts, waits for the swarm, and dies on its first Evaluate.
    with pytest.raises(ConfigError, match="genome") as info:
        Master(master_config(max_frame_size=2048), tmp_path / "run", secret=SECRET)
    assert info.value.key == "max_frame_size"
    assert not (tmp_path / "run").exists()
