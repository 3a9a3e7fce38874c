"""MAP-Elites in the grid world: its configuration refused by key, a tiny run's files and what
they say, a killed run resumed to the same archive, the study kind and the command line."""

from __future__ import annotations

import csv
import json

import numpy as np
import pandas as pd
import pytest

from gridworld.cli import main
from gridworld.config import MEASURE_NAMES, decode_run_config
from gridworld.evolve import RunFinished, evaluator_of, generation_noise_key, generation_starts
from gridworld.figures import patterns_found, patterns_found_by_group
from gridworld.patterns import PATTERNS, classify
from gridworld.qd import run_map_elites
from gridworld.tasks import check_params, run_task
from gridworld.world import Poses
from minimize_surprise.errors import ConfigError
from minimize_surprise.genetic import reduce_repetitions

TINY = {"size": 8, "agents": 16, "repetitions": 2, "steps": 25, "population": 6}
MEASURES = [{"name": "LN", "bins": 3}, {"name": "PR", "range": [0.0, 0.5], "bins": 2},
            {"name": "RD", "bins": 2}]  # fmt: skip
QD = {**TINY, "optimizer": "map-elites", "generations": 4, "measures": MEASURES}


def test_measure_names_are_the_patterns():
    assert MEASURE_NAMES == PATTERNS


@pytest.mark.parametrize(
    ("params", "key", "message"),
    [
        ({"measures": [{"name": "lines"}]}, "measures[0].name", "unknown pattern 'lines'"),
        ({"measures": [{"name": "LN", "range": [0.6, 0.2]}]}, "measures[0].range", "non-empty"),
        ({"measures": [{"name": "PR", "range": [0.3, 0.3]}]}, "measures[0].range", "non-empty"),
        ({"measures": [{"name": "PR", "range": [0.0, 1.5]}]}, "measures[0].range", "within"),
        ({"measures": [{"name": "LN"}, {"name": "RD", "bins": 0}]}, "measures[1].bins", ">= 1"),
        ({"measures": [{"name": "LN", "range": [0.5]}]}, "measures[0].range", "length 2"),
        ({"measures": [{"name": "LN", "cells": 3}]}, "measures[0].cells", "unknown key"),
        ({"measures": [{"name": "LN"}, {"name": "LN"}]}, "measures[1].name", "already"),
        ({"measures": []}, "measures", "at least one"),
        ({"measures": [{"name": p, "bins": 10} for p in ("LN", "PR", "RD", "AG", "CL", "LG")]},
         "measures", "at most 100000"),
        ({"sigma": 0}, "sigma", "> 0"),
        ({"optimizer": "ga"}, "optimizer", "does not match the kind"),
        ({"novelty": True}, "optimizer", "novelty search"),
    ],
)  # fmt: skip
def test_bad_measures_are_refused_by_key(params, key, message):
    with pytest.raises(ConfigError, match=message) as caught:
        check_params("grid-qd", params)
    assert caught.value.key == key


def test_the_ga_refuses_measures_and_the_qd_optimizer():
    with pytest.raises(ConfigError) as caught:
        decode_run_config({"measures": [{"name": "LN"}]}, file="run.yaml")
    assert (caught.value.file, caught.value.key) == ("run.yaml", "measures")
    with pytest.raises(ConfigError) as caught:
        check_params("grid-evolved", {"optimizer": "map-elites"})
    assert caught.value.key == "optimizer"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    run = tmp_path_factory.mktemp("qd")
    summary = run_map_elites(decode_run_config(QD), 5, run, checkpoint_seconds=0)
    return run, summary


def _archive(run):
    with (run / "archive.csv").open() as f:
        return list(csv.DictReader(f))


def test_a_tiny_run_writes_the_archive_and_its_elites(tiny):
    run, summary = tiny
    for name in ("archive.csv", "archive_heatmap.png", "archive_heatmap.pdf", "qd_progress.csv",
                 "qd_progress.png", "elites.json", "best_genome.json", "final_grid.json",
                 "final_grid.png", "summary.json"):  # fmt: skip
        assert (run / name).stat().st_size > 0, name
    rows = _archive(run)
    assert len(rows) == summary["elites"] >= 1
    assert summary["cells"] == 3 * 2 * 2
    assert summary["coverage"] == pytest.approx(len(rows) / 12)
    assert summary["qd_score"] == pytest.approx(sum(float(r["fitness"]) for r in rows))
    assert summary["evaluations"] == 4 * 6
    # One elite per cell, its measures its own pattern scores, its class their classification.
    assert len({r["cell"] for r in rows}) == len(rows)
    for r in rows:
        assert float(r["measure_LN"]) == float(r["score_LN"])
        assert float(r["measure_PR"]) == float(r["score_PR"])
        assert r["pattern"] in PATTERNS
        assert float(r["quality"]) == max(float(r[f"score_{p}"]) for p in PATTERNS)
        assert len([k for k in r if k.startswith("gene_")]) == 616
    found = sorted({r["pattern"] for r in rows}, key=PATTERNS.index)
    assert summary["patterns_found"] == found and summary["pattern_count"] == len(found)
    assert sum(summary["elites_per_pattern"].values()) == len(rows)
    best = max(rows, key=lambda r: float(r["fitness"]))
    assert summary["best_fitness"] == float(best["fitness"])
    assert summary["pattern"] == best["pattern"]
    # Each class's best elite is post-evaluated into elites/<class>/, as a run's best genome.
    elites = json.loads((run / "elites.json").read_text())
    assert sorted(elites, key=PATTERNS.index) == found
    for code, entry in elites.items():
        of_class = [r for r in rows if r["pattern"] == code]
        assert entry["archive_fitness"] == max(float(r["fitness"]) for r in of_class)
        genome = json.loads((run / "elites" / code / "best_genome.json").read_text())
        assert genome["fitness"] == entry["fitness"] and len(genome["genome"]) == 616
        grid = json.loads((run / "elites" / code / "final_grid.json").read_text())
        c = classify(8, 8, Poses.from_rows(grid["final"]))
        assert (c.pattern, c.quality) == (entry["pattern"], entry["quality"])
        assert (run / "elites" / code / "final_grid.png").is_file()
    with (run / "qd_progress.csv").open() as f:
        progress = list(csv.DictReader(f))
    assert [int(p["evaluations"]) for p in progress] == [6, 12, 18, 24]
    scores = [float(p["qd_score"]) for p in progress]
    assert scores == sorted(scores)
    assert int(progress[-1]["elites"]) == len(rows)


def test_an_elites_fitness_and_measures_are_its_evaluation(tiny):
    # Run the elite again on the starts and noise of the batch that found it: the same fitness,
    # and the standing run's final grid gives the archived scores.
    run, _ = tiny
    config = decode_run_config(QD)
    evaluator = evaluator_of(config)
    for r in _archive(run):
        batch = int(r["evaluation"]) // config.population
        genome = np.array([float(r[f"gene_{k}"]) for k in range(616)])
        result = evaluator.evaluate(genome[None], generation_starts(config, 5, batch),
                                    generation_noise_key(5, batch))  # fmt: skip
        fitness, reps = reduce_repetitions(result.fitness, "min")
        assert fitness[0] == float(r["fitness"])
        c = classify(8, 8, Poses.from_cells(evaluator.torus, result.final[0, int(reps[0])]))
        assert c.pattern == r["pattern"]
        assert [c.scores[p] for p in PATTERNS] == [float(r[f"score_{p}"]) for p in PATTERNS]


def test_a_killed_run_resumes_to_the_same_archive(tiny, tmp_path):
    whole, summary = tiny
    config = decode_run_config(QD)

    def kill_after_two(report):
        if report.generation == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_map_elites(config, 5, tmp_path, checkpoint_seconds=0, progress=kill_after_two)
    checkpoint = json.loads((tmp_path / "checkpoint.json").read_text())
    assert checkpoint["batch"] == 2 and (tmp_path / checkpoint["archive"]).is_file()
    assert not (tmp_path / "summary.json").exists()
    # Killed while writing the next checkpoint: its elites written, the file naming them not.
    (tmp_path / "archive-3.npz").write_bytes(b"torn")
    resumed = run_map_elites(None, None, tmp_path)
    assert (tmp_path / "archive.csv").read_bytes() == (whole / "archive.csv").read_bytes()
    assert (tmp_path / "qd_progress.csv").read_bytes() == (whole / "qd_progress.csv").read_bytes()
    assert (tmp_path / "elites.json").read_bytes() == (whole / "elites.json").read_bytes()
    drop = ("seconds",)
    assert {k: v for k, v in resumed.items() if k not in drop} == {
        k: v for k, v in summary.items() if k not in drop
    }
    assert list(tmp_path.glob("archive-*.npz")) == [tmp_path / "archive-4.npz"]
    with pytest.raises(RunFinished):
        run_map_elites(None, None, tmp_path)


def test_the_study_kind_runs_a_tiny_task(tmp_path):
    params = {k: v for k, v in QD.items() if k != "optimizer"}
    summary = run_task("grid-qd", {**params, "generations": 2}, 2, tmp_path / "run")
    assert summary["kind"] == "grid-qd" and summary["seed"] == 2
    assert summary["evaluations"] == 12 and summary["elites"] >= 1
    assert (tmp_path / "run" / "archive.csv").is_file()
    again = run_task("grid-qd", {**params, "generations": 2}, 2, tmp_path / "run")
    assert again["archive_file"] == "archive.csv" and again["elites"] == summary["elites"]


def test_patterns_found_by_group(tmp_path):
    frame = pd.DataFrame({
        "group": ["ga", "ga", "ga", "qd"],
        "kind": ["grid-evolved"] * 3 + ["grid-qd"],
        "_summary": [{"pattern": "AG"}, {"pattern": "LN"}, {"pattern": "AG"},
                     {"elites_per_pattern": {"PR": 3, "AG": 1, "TL": 2}, "evaluations": 30,
                      "post_patterns_found": ["AG", "PR"]}],
    })  # fmt: skip
    rows = {r["group"]: r for r in patterns_found(frame)}
    assert rows["ga"]["found"] == ["AG", "LN"] and rows["ga"]["per_pattern"] == {"AG": 2, "LN": 1}
    assert rows["qd"]["found"] == ["AG", "PR", "TL"] and rows["qd"]["count"] == 3
    assert rows["qd"]["post"] == ["AG", "PR"] and rows["qd"]["evaluations"] == 30
    paths = patterns_found_by_group(frame, tmp_path / "found")
    table = pd.read_csv(tmp_path / "found.csv")
    assert list(table["count"]) == [2, 3] and (tmp_path / "found.png") in paths


def test_the_command_line_runs_and_resumes_map_elites(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["evolve", "--optimizer", "map-elites", "--size", "8", "--agents", "16",
            "--repetitions", "2", "--steps", "20", "--population", "4", "--generations", "2",
            "--measure", "LN:3", "--measure", "PR:0:0.5:2", "--seed", "4",
            "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "archive:" in printed and "elites of 6 cells" in printed
    config = json.loads((out / "config.json").read_text())["config"]
    assert config["optimizer"] == "map-elites" and config["measures"][1]["range"] == [0.0, 0.5]
    assert main(["evolve", "--out", str(out)]) == 0
    assert "the run is finished" in capsys.readouterr().out
    assert main(["evolve", "--optimizer", "map-elites", "--measure", "XY:3",
                 "--out", str(tmp_path / "bad")]) == 2  # fmt: skip
    assert "measures[0].name" in capsys.readouterr().err
    assert main(["evolve", "--measure", "LN:x", "--out", str(tmp_path / "bad")]) == 2
    assert "--measure" in capsys.readouterr().err
