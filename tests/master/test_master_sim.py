"""``surprise-master sim`` and ``baseline``: the whole system on one machine, lockstep.

The master and real agents on simulated Thymios talk over loopback TCP. A run completes with a
complete run directory, its fitness rises, and it repeats exactly for a seed.
"""

from __future__ import annotations

import asyncio
import csv
import json

import msgspec
import pytest

from master_service.cli import main
from master_service.experiments.baseline import run_baseline
from master_service.experiments.simulate import SimulatedSwarm, simulation_experiment
from minimize_surprise.config import load_experiment
from minimize_surprise.errors import ConfigError


def small(scenario: str = "basic", evaluations: int = 60, **kw):
    experiment = simulation_experiment(scenario, robots=4, evaluations=evaluations, seed=2)
    return msgspec.structs.replace(experiment, post_evaluation_steps=60, **kw)


def rows(run) -> list[dict[str, str]]:
    with open(run / "evaluations.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def basic_run(tmp_path_factory):
    """One lockstep run of 4 robots in the basic arena, 60 evaluations of 100 steps."""
    run = tmp_path_factory.mktemp("sim") / "run"
    result = asyncio.run(SimulatedSwarm(small()).run(run))
    return run, result


def test_a_lockstep_run_completes_with_a_complete_run_directory(basic_run):
    run, result = basic_run
    table = rows(run)
    assert [int(r["evaluation"]) for r in table] == list(range(1, 61))
    assert all(r["attempts"] == "1" for r in table)  # nothing was lost in a healthy swarm
    assert {f"fitness_sim-{i}" for i in range(4)} <= set(table[0])
    for name in ("config.yaml", "checkpoint.json", "best_genome.json", "master.log",
                 "post_evaluation.json", "metrics.json", "simulation.json"):  # fmt: skip
        assert (run / name).is_file(), name
    assert sorted(p.name for p in (run / "traces").iterdir()) == [f"sim-{i}.npz" for i in range(4)]
    assert {p.name for p in (run / "plots").iterdir()} >= {
        f"{name}.{fmt}" for name in ("fitness", "robot_fitness", "predictions", "trajectories")
        for fmt in ("png", "pdf")
    }  # fmt: skip
    post = result.metrics["post_evaluation"]
    assert post["steps"] == 60 and set(post["robots"]) == {f"sim-{i}" for i in range(4)}
    assert post["behaviour"]["motion"] in {"stopped", "diverse", "circling"}


def test_fitness_rises_over_the_run(basic_run):
    run, result = basic_run
    fitness = [float(r["fitness"]) for r in rows(run)]
    best = [float(r["best_fitness"]) for r in rows(run)]
    assert best[-1] > fitness[0] + 0.02
    assert sum(fitness[-15:]) / 15 > sum(fitness[:15]) / 15
    assert result.summary.best_fitness == pytest.approx(best[-1])


def test_the_same_seed_gives_the_same_run(basic_run, tmp_path):
    run, _ = basic_run
    asyncio.run(SimulatedSwarm(small()).run(tmp_path / "again"))
    columns = ("evaluation", "kind", "fitness", "best_fitness", "accepted")
    first = [[r[c] for c in columns if c in r] + [v for k, v in r.items() if k.startswith("fit")]
             for r in rows(run)]  # fmt: skip
    again = [[r[c] for c in columns if c in r] + [v for k, v in r.items() if k.startswith("fit")]
             for r in rows(tmp_path / "again")]  # fmt: skip
    assert first == again


def test_simulated_agents_run_whatever_period_the_experiment_gives(tmp_path):
    # A real Thymio's 10 Hz sensors set a real robot's shortest step, not a simulated body's: a
    # simulation at 100 Hz runs, it is not refused by its own agents.
    experiment = small(evaluations=3, step_period=0.01)
    # (A refusing swarm would repeat the first round forever: bounded.)
    result = asyncio.run(asyncio.wait_for(SimulatedSwarm(experiment).run(tmp_path / "run"), 60))
    assert result.summary.evaluations == 3 and result.summary.failed_attempts == 0


def test_object_manipulation_measures_box_displacement(tmp_path):
    experiment = small("boxes", evaluations=3)
    result = asyncio.run(SimulatedSwarm(experiment).run(tmp_path / "run"))
    behaviour = result.metrics["post_evaluation"]["behaviour"]
    assert behaviour["box_displacement"] is not None and behaviour["pushing"] is not None
    boxes = json.loads((tmp_path / "run" / "simulation.json").read_text())
    assert len(boxes["post_evaluation_boxes"]["start"]) == boxes["world"]["boxes"] > 100


def test_experiment_layers_scenario_file_and_options(tmp_path):
    assert simulation_experiment("gradient").sensors[-2:] == ["light.0", "light.1"]
    assert simulation_experiment("gradient").robots == 4
    assert simulation_experiment("basic").robots == 10
    path = tmp_path / "exp.yaml"
    path.write_text("scenario: boxes\nevaluation_steps: 50\nevolution: {mutation_range: 0.3}\n")
    exp = simulation_experiment(None, config_file=path, evaluations=7, seed=5)
    assert exp.scenario == "boxes" and "force" in exp.sensors and exp.evaluation_steps == 50
    assert exp.evolution.evaluations == 7 and exp.evolution.mutation_range == 0.3
    assert exp.seed == 5


@pytest.mark.parametrize(
    "text, key",
    [
        ("sensors: [ir.f0, force]", "sensors"),  # basic robots carry no force sensor
        ("simulation: {arena_side: -1}", "simulation.arena_side"),
        ("scenario: moon", "scenario"),
        ("evolution: {evaluations: 0}", "evolution.evaluations"),
    ],
)
def test_bad_experiment_names_file_and_key(tmp_path, text, key):
    path = tmp_path / "exp.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        simulation_experiment(None, config_file=path)
    assert info.value.key == key and info.value.file == str(path)


def test_baseline_is_reproducible_and_report_compares(basic_run, tmp_path, capsys):
    run, _ = basic_run
    experiment = small()
    first = run_baseline(experiment, 3, tmp_path / "base")
    again = run_baseline(experiment, 3, tmp_path / "again")
    assert [p["fitness"] for p in first["pairs"]] == [p["fitness"] for p in again["pairs"]]
    assert all(0.0 < p["fitness"] < 1.0 for p in first["pairs"])
    fitness = [p["fitness"] for p in first["pairs"]]
    assert first["best_fitness"] == max(fitness)
    motions = [p["behaviour"]["motion"] for p in first["pairs"]]
    assert first["behaviour_counts"]["motion"] == {m: motions.count(m) for m in set(motions)}
    assert main(["report", str(run), "--baseline", str(tmp_path / "base")]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    comparison = metrics["baseline"]
    assert comparison["random_pairs"] == 3
    assert comparison["random_median_fitness"] == pytest.approx(first["median_fitness"])
    # Best of the run against best of the random pairs, both maxima over many tries.
    assert comparison["random_best_fitness"] == max(fitness)
    best = metrics["best_fitness"]
    assert comparison["random_pairs_below_evolved_best"] == sum(f < best for f in fitness)
    assert comparison["evolved_post_fitness"] == metrics["post_evaluation"]["swarm_fitness"]
    out = capsys.readouterr().out
    assert f"evolved best fitness {best:.4f} against the best random pair {max(fitness):.4f}" in out
    assert (run / "plots" / "evolved_vs_random.png").is_file()
    assert (run / "plots" / "evolved_vs_random.pdf").is_file()


def test_baseline_command_names_the_counts_and_the_next_command(tmp_path, capsys):
    out = tmp_path / "base"
    argv = ["baseline", "--scenario", "basic", "--robots", "3", "--random", "2", "--out", str(out)]
    assert main(argv) == 0
    lines = capsys.readouterr().out.splitlines()
    data = json.loads((out / "baseline.json").read_text())
    assert lines[0].startswith("evaluating 2 random pairs in the basic arena")
    assert lines[1] == (
        f"fitness of the random pairs: best {data['best_fitness']:.4f}, median "
        f"{data['median_fitness']:.4f}"
    )
    assert lines[2].startswith("behaviour counts: motion ")
    assert sum(data["behaviour_counts"]["motion"].values()) == 2
    assert lines[-1] == (
        f"next: compare an evolved run with `surprise-master report RUN_DIR --baseline {out}`"
    )


def test_report_refuses_a_baseline_of_another_scenario(basic_run, tmp_path):
    run, _ = basic_run
    run_baseline(small("boxes"), 1, tmp_path / "base")
    assert main(["report", str(run), "--baseline", str(tmp_path / "base")]) == 2


def test_sim_command_prints_the_summary(tmp_path, capsys):
    out = tmp_path / "run"
    code = main(["sim", "--robots", "3", "--evaluations", "4", "--seed", "1", "--out", str(out)])
    assert code == 0
    text = capsys.readouterr().out
    assert f"run directory: {out}" in text and "best fitness: 0." in text
    assert "behaviour: " in text and (out / "metrics.json").is_file()
    assert "safety layer drove: " in text
    assert "simulating basic (paper setting, fast engine): 3 robots, 4 evaluations" in text


@pytest.mark.parametrize(
    "argv, words",
    [(["--robots", "0"], "--robots"), (["--config", "missing.yaml"], "cannot read")],
)
def test_sim_command_refuses_bad_options(tmp_path, capsys, argv, words):
    assert main(["sim", "--out", str(tmp_path / "run"), *argv]) == 2
    assert words in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_an_experiment_without_a_setting_is_lab_for_sim_as_for_the_robots(tmp_path, capsys):
    path = tmp_path / "exp.yaml"
    path.write_text("robots: 3\nevolution: {evaluations: 2}\npost_evaluation_steps: 20\n")
    # As `surprise-master run` reads it: the lab setting.
    assert load_experiment(path).setting == "lab"
    out = tmp_path / "run"
    assert main(["sim", "--config", str(path), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "simulating basic (lab setting" in captured.out
    assert f"note: {path} names no setting: lab" in captured.err
    assert simulation_experiment(None, config_file=path).step_period == 0.1
    # Without a file, and with --setting, no note: the command says which.
    assert simulation_experiment("basic").setting == "paper"
    assert main(["sim", "--config", str(path), "--setting", "paper", "--out", str(out / "p")]) == 0
    captured = capsys.readouterr()
    assert "paper setting" in captured.out and "note:" not in captured.err
