"""A study's recorded group: finished run directories (the lab's real-robot runs) read, never
written, and reported beside a simulated group, with a run that cannot be used named and left
out; a recorded group's bad params are one error naming the study file and the key.

Short simulated runs stand in for the lab's: their simulation.json, box track, report and the
poses of their traces taken away, as a real run has none (tests/master/test_tracker_positions.py
does the same); one of them has a tracker's metrics.json, as `surprise-master report RUN
--positions` writes it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from study_helpers import write_study

from master_service.experiments.engine_run import FastRun
from master_service.experiments.simulation_setup import simulation_experiment
from minimize_surprise.errors import ConfigError
from reporting.report import compute_metrics
from studies.executors import LocalPool
from studies.report import PROBLEMS, write_study_report
from studies.runner import prepare, run_study
from studies.spec import expand, load_study

pytestmark = pytest.mark.slow

#: The Sec. V-C experiment, made tiny: 3 evaluations of 8 steps, a post-evaluation of 12.
PARAMS = {
    "setting": "lab",
    "scenario": "boxes",
    "arena": "real-objects",
    "robots": 4,
    "evaluation_steps": 8,
    "post_evaluation_steps": 12,
    "evolution": {"evaluations": 3},
}

STUDY = f"""
name: lab
defaults: {{plots: false}}
groups:
  - name: real
    kind: recorded
    params: {{runs: ["lab-runs/run-*"]}}
    paper: {{median_fitness_at_least: 0.01, classes: "3 circling, 1 reverse driving"}}
  - name: sim
    kind: evolved
    params: {json.dumps(PARAMS)}
    seeds: 2
"""


def _lab_run(directory: Path, seed: int) -> dict:
    """A short simulated run in ``directory``, then made to look real (no poses, no
    simulation.json, no report); the behaviour its poses gave."""
    experiment = simulation_experiment(data=dict(PARAMS), seed=seed)
    FastRun(experiment).run(directory, plots=False)
    behaviour = compute_metrics(directory)["post_evaluation"]["behaviour"]
    for name in ("simulation.json", "box_track.npz", "metrics.json"):
        (directory / name).unlink(missing_ok=True)
    shutil.rmtree(directory / "plots", ignore_errors=True)
    for path in (directory / "traces").iterdir():
        with np.load(path) as data:
            arrays = {key: data[key] for key in data.files if key != "poses"}
        np.savez_compressed(path, **arrays)
    return behaviour


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> Path:
    """A study folder: the study file and ``lab-runs/`` with three finished real-looking runs,
    one tracked (its metrics.json holds a behaviour), one unfinished and one of a newer format."""
    root = tmp_path_factory.mktemp("lab")
    runs = root / "lab-runs"
    behaviours = {seed: _lab_run(runs / f"run-{seed}", seed) for seed in (1, 2, 3)}
    tracked = runs / "run-1"
    behaviour = behaviours[1]
    (tracked / "metrics.json").write_text(
        json.dumps({"post_evaluation": {"behaviour": behaviour, "positions": {"file": "t.csv"}}})
    )
    unfinished = shutil.copytree(runs / "run-3", runs / "run-4")
    (unfinished / "post_evaluation.json").unlink()
    newer = shutil.copytree(runs / "run-3", runs / "run-5")
    post = json.loads((newer / "post_evaluation.json").read_text())
    (newer / "post_evaluation.json").write_text(json.dumps({**post, "format": 99}))
    write_study(root, STUDY, "lab.yaml")
    return root


def _files(directory: Path) -> dict[str, tuple[int, int]]:
    return {
        str(p.relative_to(directory)): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in sorted(directory.rglob("*"))
    }


def test_a_recorded_group_is_reported_beside_a_simulated_one(lab, tmp_path):
    before = _files(lab / "lab-runs")
    pool = LocalPool(1)
    try:
        counts = run_study(lab / "lab.yaml", tmp_path / "study", pool)
    finally:
        pool.close()
    # Two runs of the lab cannot be used: they fail alone, the study goes on.
    assert (counts.done, counts.failed) == (5, 2)
    result = write_study_report(tmp_path / "study")
    report = tmp_path / "study" / "report"
    assert _files(lab / "lab-runs") == before  # read, never written

    summary = pd.read_csv(report / "summary.csv").set_index("group")
    assert summary.loc["real", "kind"] == "recorded" and summary.loc["real", "runs"] == 3
    assert summary.loc["sim", "runs"] == 2
    best = [
        pd.read_csv(lab / "lab-runs" / f"run-{i}" / "evaluations.csv")["best_fitness"].iloc[-1]
        for i in (1, 2, 3)
    ]
    assert summary.loc["real", "median_fitness"] == pytest.approx(float(np.median(best)))
    assert summary.loc["real", "q1_fitness"] == pytest.approx(np.percentile(best, 25))
    # Two real runs have no class (no positions), the tracked one its metrics.json's.
    assert summary.loc["real", "n_unknown"] == 2

    runs = pd.read_csv(report / "runs.csv").set_index("run")
    assert runs.loc["real/run-1", "source"] == str(lab / "lab-runs" / "run-1")
    assert runs.loc["real/run-1", "behaviour"] not in ("unknown", None)
    assert runs.loc["real/run-2", "behaviour"] == "unknown"
    assert "--positions" in runs.loc["real/run-2", "behaviour_missing"]
    assert bool(runs.loc["real/run-2", "real"]) and runs.loc["real/run-2", "safety_share"] >= 0

    problems = (report / PROBLEMS).read_text().splitlines()
    assert problems == result["problems"] and len(problems) == 2
    assert f"{lab / 'lab-runs' / 'run-4'} is unfinished: no post-evaluation" in problems[0]
    assert f"{lab / 'lab-runs' / 'run-5'} is unreadable" in problems[1]
    assert "format 99" in problems[1]

    assert (report / "figures" / "fitness_over_evaluations.png").is_file()
    curves = pd.read_parquet(report / "evaluations.parquet")
    assert set(curves.loc[curves["kind"] == "recorded", "run"]) == {
        f"real/run-{i}" for i in (1, 2, 3)
    }
    tests = pd.read_csv(report / "statistics.csv")
    assert "real vs sim" in set(tests.loc[tests["test"] == "mann-whitney-u", "samples"])
    paper = pd.read_csv(report / "paper.csv")
    assert list(paper["group"]) == ["real"] and bool(paper["holds"][0])


def test_a_run_the_lab_adds_joins_the_study(lab, tmp_path):
    study = write_study(tmp_path, STUDY.replace("lab-runs/", f"{lab}/lab-runs/"), "more.yaml")
    before = [t["run"] for t in prepare(study, tmp_path / "out")]
    (lab / "lab-runs" / "run-6").mkdir()
    try:
        after = [t["run"] for t in prepare(study, tmp_path / "out")]  # not refused
    finally:
        (lab / "lab-runs" / "run-6").rmdir()
    assert after == [*before[:5], "real/run-6", *before[5:]]


def _study(tmp_path: Path, group: str) -> Path:
    (tmp_path / "lab-runs" / "run-1").mkdir(parents=True)
    return write_study(tmp_path, f"name: x\ngroups:\n  - {group}\n")


@pytest.mark.parametrize(
    ("group", "key", "words"),
    [
        ("{name: r, kind: recorded, params: {runs: [lab-runs/run-1]}, seeds: 2}",
         "groups[0].seeds", "no seeds"),
        ("{name: r, kind: recorded, params: {runs: [lab-runs/run-1]}, sweep: {robots: [4]}}",
         "groups[0].sweep", "no sweep"),
        ("{name: r, kind: recorded}", "groups[0].params.runs", "required key is missing"),
        ("{name: r, kind: recorded, params: {runs: []}}", "groups[0].params.runs", ""),
        ("{name: r, kind: recorded, params: {runs: [a], seed: 3}}", "groups[0].params.seed",
         "unknown key"),
    ],
)  # fmt: skip
def test_a_bad_recorded_group_names_the_file_and_key(tmp_path, group, key, words):
    path = _study(tmp_path, group)
    with pytest.raises(ConfigError) as info:
        load_study(path)
    assert (info.value.file, info.value.key) == (str(path), key)
    assert words in str(info.value)


def test_a_path_that_matches_no_run_is_refused_before_anything_runs(tmp_path):
    path = _study(
        tmp_path, "{name: r, kind: recorded, params: {runs: [lab-runs/run-*, lab/run-*]}}"
    )
    assert len(expand(load_study(path))) == 1  # loads (and lists): the lab may record later
    with pytest.raises(ConfigError) as info:
        prepare(path, tmp_path / "out")
    assert (info.value.file, info.value.key) == (str(path), "groups[0].params.runs[1]")
    assert "lab/run-*" in str(info.value) and not (tmp_path / "out").exists()


def test_the_shipped_example_finds_the_lab_runs_beside_its_folder(tmp_path):
    from studies.runner import find_study

    shipped = find_study("paper-sec5-real")
    tasks = expand(load_study(shipped))  # no lab runs beside the package: the simulated four
    assert [t["seed"] for t in tasks] == [1, 2, 3, 4]
    params = tasks[0]["params"]
    assert (params["setting"], params["scenario"], params["arena"]) == (
        "lab",
        "boxes",
        "real-objects",
    )
    assert (params["robots"], params["evolution"]["evaluations"]) == (4, 350)
    (tmp_path / "studies").mkdir()
    copy = Path(shutil.copy(shipped, tmp_path / "studies"))
    for name in ("run-1", "run-2", "run-10", "notes"):
        (tmp_path / "lab-runs" / name).mkdir(parents=True)
    real = [t for t in expand(load_study(copy, find_runs=True)) if t["kind"] == "recorded"]
    assert [t["run"] for t in real] == ["real/run-1", "real/run-10", "real/run-2"]
    assert real[0]["params"] == {"source": str(tmp_path / "lab-runs" / "run-1")}
