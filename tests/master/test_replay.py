"""``surprise-master replay``: a stored genome driven again without evolution, on simulated
robots (either engine) or a master's robots, and the reality gap beside its source run."""

from __future__ import annotations

import json
from pathlib import Path

import msgspec
import pytest

from master_service.cli import main
from master_service.experiments.engine_run import FastRun
from master_service.experiments.simulate import simulation_experiment
from runfiles.schema import Replay

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module", params=["basic", "boxes"])
def source(tmp_path_factory, request) -> Path:
    """A short simulated run of the paper's basic scenario (the stop profile) or the boxes one
    (the escape profile, whose random turns go on from the evolution's): 3 robots, 30
    evaluations."""
    experiment = simulation_experiment(request.param, setting="paper", robots=3, seed=6)
    experiment = msgspec.structs.replace(
        experiment,
        evolution=msgspec.structs.replace(experiment.evolution, evaluations=30),
        evaluation_steps=60,
        post_evaluation_steps=200,
    )
    run = tmp_path_factory.mktemp("source") / "run"
    FastRun(experiment).run(run, plots=False)
    return run


@pytest.mark.parametrize("engine", ["fast", "agents"])
def test_a_replay_on_simulated_robots_reproduces_the_post_evaluation(
    source: Path, tmp_path: Path, engine: str, capsys
):
    out = tmp_path / "replay"
    assert main(["replay", str(source), "--out", str(out), "--engine", engine]) == 0
    printed = capsys.readouterr().out
    original = json.loads((source / "post_evaluation.json").read_text())
    replayed = json.loads((out / "post_evaluation.json").read_text())
    assert replayed["swarm_fitness"] == original["swarm_fitness"]
    assert {r: v["fitness"] for r, v in replayed["robots"].items()} == {
        r: v["fitness"] for r, v in original["robots"].items()
    }
    # No evolution: no row, the genome as the best one, where it came from.
    assert (
        not (out / "evaluations.csv").exists()
        or len((out / "evaluations.csv").read_text().splitlines()) <= 1
    )
    assert (
        json.loads((out / "best_genome.json").read_text())["genome"]
        == json.loads((source / "best_genome.json").read_text())["genome"]
    )
    assert json.loads((out / Replay.FILE).read_text())["source_run"] == str(source.resolve())
    gap = json.loads((out / "metrics.json").read_text())["reality_gap"]
    assert gap["swarm_fitness"]["gap"] == 0.0
    assert gap["behaviour"]["source"] == gap["behaviour"]["replay"]
    assert "gap in swarm fitness: +0.0000" in printed
    assert (out / "plots" / "reality_gap.png").is_file()


def test_a_genome_that_does_not_fit_the_experiment_is_refused_naming_what_differs(
    source: Path, tmp_path: Path, capsys
):
    experiment = tmp_path / "lab.yaml"
    experiment.write_text("scenario: basic\nsetting: lab\nrobots: 2\n")
    out = tmp_path / "replay"
    code = main(["replay", str(source), "--experiment", str(experiment), "--out", str(out)])
    assert code == 2
    err = capsys.readouterr().err
    assert "does not fit the experiment's networks: " in err and "(genome) against" in err
    assert not out.exists()


def test_a_directory_without_a_genome_is_refused(tmp_path: Path, capsys):
    assert main(["replay", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    assert "best_genome.json does not exist: no genome to replay" in capsys.readouterr().err
