"""Experiment configuration: defaults from the paper, and one clear error per bad file."""

from __future__ import annotations

import pytest

from minimize_surprise.config import ExperimentConfig, Strict, decode, load_experiment
from minimize_surprise.errors import ConfigError


def write(tmp_path, text: str):
    path = tmp_path / "experiment.yaml"
    path.write_text(text)
    return path


def test_empty_file_gives_the_lab_settings_defaults(tmp_path):
    cfg = load_experiment(write(tmp_path, ""))
    assert cfg == ExperimentConfig()
    # The paper's real-robot runs: 350 evaluations of 100 steps at 10 Hz.
    assert cfg.evolution.evaluations == 350 and cfg.evaluation_steps == 100
    assert cfg.evolution.reevaluation_probability == 0.2
    assert cfg.evolution.mutation_probability == 0.1 and cfg.evolution.mutation_range == 0.4
    assert cfg.post_evaluation_steps == 1000 and len(cfg.sensors) == 9
    assert cfg.step_period == 0.1  # 10 Hz, the paper's control rate


def test_a_full_file_decodes(tmp_path):
    cfg = load_experiment(
        write(
            tmp_path,
            """
sensors: [ir.f0, ir.f1, ir.f2, ir.f3, ir.f4, ir.b0, ir.b1, ground.0, ground.1, force]
network: {actor_hidden: 7, predictor_hidden: 11}
evolution: {evaluations: 350, mutation_range: 0.3}
predefined: {force: 0.3}
scenario: boxes
robots: 4
seed: 9
simulation: {arena_side: 1.2}
""",
        )
    )
    assert cfg.sensors[-1] == "force" and cfg.predefined == {"force": 0.3}
    assert cfg.evolution.evaluations == 350 and cfg.network.predictor_hidden == 11
    assert cfg.simulation == {"arena_side": 1.2}


@pytest.mark.parametrize(
    "text, key, words",
    [
        ("evolution: {mutation_probability: 1.5}", "evolution.mutation_probability", "<= 1.0"),
        ("evolution: {evaluations: many}", "evolution.evaluations", "int"),
        ("network: {actor_hidden: 8, depth: 2}", "network.depth", "unknown key"),
        ("speed: 3", "speed", "unknown key"),
        ("sensors: [ir.f0, ir.f9]", "sensors", "unknown sensor 'ir.f9'"),
        ("sensors: [ir.f0, ir.f0]", "sensors", "listed twice"),
        ("predefined: {force: 0.2}", "predefined.force", "not among"),
        ("predefined: {ir.f0: 2}", "predefined.ir.f0", "in [0, 1]"),
        ("seed: -1", "seed", ">= 0"),
        ("step_period: 0", "step_period", "> 0.0"),
        ("step_period: 100", "step_period", "<= 10.0"),
        ("step_period: .inf", "step_period", "<= 10.0"),
    ],
)
def test_bad_values_name_file_and_key(tmp_path, text, key, words):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_experiment(path)
    err = info.value
    assert err.file == str(path) and err.key == key and words in str(err)
    assert str(path) in str(err) and key in str(err)
    assert isinstance(err, ValueError)


@pytest.mark.parametrize("text, words", [("a: [1, 2", "not valid YAML"), ("- 1\n- 2", "mapping")])
def test_malformed_documents(tmp_path, text, words):
    with pytest.raises(ConfigError, match=words):
        load_experiment(write(tmp_path, text))


class Inner(Strict):
    port: int


class Outer(Strict):
    master: Inner


def test_missing_required_key_is_named():
    with pytest.raises(ConfigError) as info:
        decode({"master": {}}, Outer, file="agent.yaml")
    assert info.value.key == "master.port" and "required key is missing" in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read") as info:
        load_experiment(tmp_path / "nope.yaml")
    assert info.value.file.endswith("nope.yaml")
