"""run_task for every kind on a tiny world, and surprise-grid end to end (resume included)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gridworld.cli import main
from gridworld.config import GridRunConfig
from gridworld.evolve import RunFinished, run_evolution
from gridworld.tasks import GRID_KINDS, run_task
from minimize_surprise.errors import ConfigError

TINY = {"size": 7, "agents": 12, "repetitions": 2, "steps": 30}
KEYS = {"kind", "seed", "size", "best_fitness", "fitness", "pattern", "quality", "scores",
        "mean_predictions", "generations_file", "seconds"}  # fmt: skip


@pytest.fixture(scope="module")
def evolved(tmp_path_factory):
    run = tmp_path_factory.mktemp("evolved")
    summary = run_task("grid-evolved", {**TINY, "population": 4, "generations": 2}, 7, run)
    return run, summary


def test_evolved_task(evolved):
    run, summary = evolved
    assert set(summary) >= KEYS
    assert summary["kind"] == "grid-evolved" and summary["seed"] == 7
    assert summary["best_fitness"] == summary["fitness"]
    assert len(summary["mean_predictions"]) == 14
    assert (run / summary["generations_file"]).exists()
    assert len((run / "generations.csv").read_text().splitlines()) == 3
    assert set(summary["scores"]) == {"CL", "AG", "LG", "LN", "PR", "TL", "SQ", "SW", "RD"}


@pytest.mark.parametrize(
    "kind,params",
    [
        ("grid-random", {}),
        ("grid-selected-random", {"candidates": 6}),
        ("grid-novelty", {"population": 4, "generations": 2}),
        ("grid-rerun", {"size": 9}),
    ],
)
def test_other_kinds_are_deterministic(kind, params, tmp_path, evolved):
    if kind == "grid-rerun":
        params = {**params, "genome_run": str(evolved[0]), "agents": 12, "steps": 30}
    else:
        params = {**TINY, **params}
    a = run_task(kind, params, 3, tmp_path / "a")
    b = run_task(kind, params, 3, tmp_path / "b")
    assert set(a) >= KEYS
    for key in ("fitness", "pattern", "quality", "scores", "mean_predictions"):
        assert a[key] == b[key], key
    if kind == "grid-novelty":
        assert a["fitness"] is None
        assert a["individuals"] == 8
        assert (tmp_path / "a" / "individuals.csv").exists()
        assert set(a["quality_best"]) == {"generation", "index", "pattern", "quality"}
    if kind == "grid-selected-random":
        single = run_task("grid-random", {**TINY}, 3, tmp_path / "c")
        assert a["fitness"] >= 0 and single["fitness"] >= 0


def test_damage_task(evolved, tmp_path):
    run, _ = evolved
    params = {"genome_run": str(run), "steps": 30, "xmin": 0, "xmax": 3, "ymin": 0, "ymax": 3}
    removed = run_task("grid-damage", params, 1, tmp_path / "r")
    assert removed["variant"] == "remove"
    assert 0.0 <= removed["similarity"] <= 1.0
    moved = run_task("grid-damage", {**params, "variant": "reposition"}, 1, tmp_path / "p")
    again = run_task("grid-damage", {**params, "variant": "reposition"}, 1, tmp_path / "q")
    assert moved["similarity"] == again["similarity"]
    assert moved["removed"] == removed["removed"]
    data = json.loads((tmp_path / "p" / "damage.json").read_text())
    assert len(data["damaged"]) == len(data["initial"])
    assert len({tuple(p[:2]) for p in data["damaged"]}) == len(data["damaged"])


def test_bad_params_name_the_key(tmp_path):
    with pytest.raises(ConfigError, match="popsize"):
        run_task("grid-evolved", {"popsize": 3}, 1, tmp_path)
    with pytest.raises(ConfigError, match="noise"):
        run_task("grid-random", {"noise": 2.0}, 1, tmp_path)
    with pytest.raises(ConfigError, match="agents"):
        run_task("grid-evolved", {"size": 5, "agents": 30}, 1, tmp_path)
    with pytest.raises(ConfigError, match="unknown kind"):
        run_task("grid-magic", {}, 1, tmp_path)
    with pytest.raises(ConfigError, match="genome"):
        run_task("grid-rerun", {}, 1, tmp_path)
    assert len(GRID_KINDS) == 7 and "grid-qd" in GRID_KINDS


def test_evolve_resumes_bit_for_bit_and_knows_when_it_is_finished(tmp_path, capsys):
    args = ["--size", "7", "--agents", "12", "--population", "4", "--generations", "4",
            "--repetitions", "2", "--steps", "30", "--seed", "5"]  # fmt: skip
    assert main(["evolve", *args, "--out", str(tmp_path / "whole")]) == 0
    # the same run, stopped after two generations, then continued by the command line
    config = GridRunConfig(size=7, agents=12, population=4, generations=4, repetitions=2,
                           steps=30)  # fmt: skip

    def stop(report):
        if report.generation == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_evolution(config, 5, tmp_path / "part", progress=stop, plots=False)
    assert main(["evolve", "--out", str(tmp_path / "part")]) == 0
    for name in ("generations.csv", "best_genome.json", "final_grid.json"):
        assert (tmp_path / "whole" / name).read_text() == (tmp_path / "part" / name).read_text()
    summary = json.loads((tmp_path / "part" / "summary.json").read_text())
    for ext in ("png", "pdf"):
        assert (tmp_path / "part" / f"fitness.{ext}").exists()
        assert (tmp_path / "part" / f"final_grid.{ext}").exists()
    capsys.readouterr()
    assert main(["evolve", "--out", str(tmp_path / "part")]) == 0
    assert "finished" in capsys.readouterr().out
    with pytest.raises(RunFinished):
        run_evolution(None, None, tmp_path / "part")
    assert summary["pattern"] in summary["scores"]


def test_replay_and_classify(tmp_path, capsys, evolved):
    run, summary = evolved
    assert main(["replay", str(run), "--every", "10"]) == 0
    assert (run / "replay.gif").stat().st_size > 0
    assert (run / "replay_final.png").exists()
    assert f"{summary['fitness']:.4f}" in capsys.readouterr().out
    assert main(["classify", str(run / "final_grid.json")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["pattern"] == summary["pattern"] and out["scores"] == summary["scores"]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"width": 5, "height": 5, "final": [[0, 0, 1, 1]]}))
    assert main(["classify", str(bad)]) == 2
    assert "key 'final'" in capsys.readouterr().err
    assert main(["evolve", "--size", "3", "--out", str(tmp_path / "x")]) == 2
    assert "agents" in capsys.readouterr().err


def test_a_runs_best_genome_loads_with_its_spec(tmp_path):
    # an actor-only (novelty) genome is shorter than a full pair: its spec must come back whole
    from gridworld.evolve import load_best, write_best, write_final_grid
    from minimize_surprise.gridnet import GridGenomeLayout, GridNetSpec

    spec = GridNetSpec(14, None, True)
    genome = np.arange(GridGenomeLayout(spec).size, dtype=np.float64)
    write_best(tmp_path, genome, spec, 0.5, generation=3)
    write_final_grid(tmp_path, 15, 15, 2, [[0, 0, 1, 0]], [[1, 0, 1, 0]])
    loaded, loaded_spec, grid = load_best(tmp_path)
    assert loaded_spec == spec and GridGenomeLayout(loaded_spec).size == genome.size
    np.testing.assert_array_equal(loaded, genome)
    assert grid["repetition"] == 2 and grid["final"] == [[1, 0, 1, 0]]
