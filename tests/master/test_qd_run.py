"""MAP-Elites on the engine (``sim --optimizer map-elites``): its configuration refused by key,
its archive's elites what their genomes do, its files, its checkpoint and resume, its study
kind (docs/quality-diversity.md)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from master_service.cli import main
from master_service.experiments.qd_run import QDRun, behaviour_class, qd_experiment
from master_service.experiments.simulation_setup import simulation_experiment
from minimize_surprise.config import decode_experiment
from minimize_surprise.errors import ConfigError
from runfiles import schema
from runfiles.schema import ARCHIVE, QD_PROGRESS, PostEvaluation, QDSummary
from simulator import metrics as sm

#: A run of seconds: 4 robots, 100-step evaluations, 3 batches of 4 candidates.
TINY = {
    "setting": "paper",
    "scenario": "basic",
    "robots": 4,
    "evaluation_steps": 100,
    "post_evaluation_steps": 100,
    "evolution": {"evaluations": 12},
    "optimizer": {
        "name": "map-elites",
        "batch": 4,
        "measures": [
            {"name": "rotation", "range": [0, 130], "bins": 13},
            {"name": "mean_cluster_size", "range": [1.0, 4.0], "bins": 6},
        ],
    },
}


def _experiment(seed: int = 5, **changes):
    return simulation_experiment(data={**TINY, **changes}, seed=seed)


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(encoding="utf-8") as file:
        return list(csv.DictReader(file))


def _axis(name: str = "rotation", low: float = 0.0, high: float = 1.0, bins: int = 2) -> dict:
    return {"name": name, "range": [low, high], "bins": bins}


@pytest.mark.parametrize(
    ("optimizer", "key", "words"),
    [
        ({"measures": [_axis("spin")]}, "measures[0].name", "unknown measure 'spin'"),
        ({"measures": [_axis(low=5, high=5)]}, "measures[0].range", "low < high"),
        ({"measures": [_axis(low=9, high=1)]}, "measures[0].range", "low < high"),
        ({"measures": [_axis(bins=0)]}, "measures[0].bins", ">= 1"),
        ({"measures": [_axis(), _axis()]}, "measures", "named twice"),
        ({"measures": []}, "measures", "at least one"),
        ({"batch": 0}, "batch", ">= 1"),
        ({"name": "cma"}, "name", "Invalid enum value .cma."),
        ({"sigmas": 1}, "sigmas", "unknown key"),
    ],
)
def test_a_bad_optimizer_section_is_refused_naming_the_file_and_key(optimizer, key, words):
    with pytest.raises(ConfigError, match=words) as caught:
        decode_experiment({"optimizer": optimizer}, file="qd.yaml")
    assert caught.value.key == f"optimizer.{key}"
    assert "qd.yaml" in str(caught.value)


def test_box_displacement_in_an_arena_without_boxes_is_refused_by_key():
    measures = [_axis(), _axis("box_displacement")]
    experiment = _experiment(optimizer={"name": "map-elites", "measures": measures})
    with pytest.raises(ConfigError, match="d_B needs boxes") as caught:
        qd_experiment(experiment)
    assert caught.value.key == "optimizer.measures[1].name"


def test_an_endless_budget_or_arena_events_are_refused_by_key():
    endless = _experiment(optimizer={"name": "map-elites"}, evolution={"evaluations": None})
    with pytest.raises(ConfigError, match="needs a budget") as caught:
        qd_experiment(endless)
    assert caught.value.key == "evolution.evaluations"
    events = [{"kind": "light-moves", "evaluation": 5, "position": [0.1, 0.1]}]
    changing = _experiment(optimizer={"name": "map-elites"}, events=events)
    with pytest.raises(ConfigError, match="an arena of its own") as caught:
        qd_experiment(changing)
    assert caught.value.key == "events"


def test_every_elite_is_what_its_genome_does_in_its_arena(tmp_path):
    # Asked and told in batches: each elite's fitness, measures and class are those of its
    # genome evaluated again in the arena it was evaluated in, and it sits in their cell.
    run = QDRun(_experiment())
    result = run.run(tmp_path / "run", plots=False, post_evaluate=False)
    assert result is not None
    rows = _rows(tmp_path / "run" / ARCHIVE)
    assert 1 < len(rows) <= 12 and len({r["cell"] for r in rows}) == len(rows)
    again = QDRun(_experiment())
    for row in rows:
        genome = np.array(json.loads(row["genome"]))
        seed = int(row["arena_seed"])
        index = next(i for i in range(12) if run.arena_seed(i) == seed)
        fitness, (behaviour,) = again.evaluate(genome[None], index)
        assert fitness[0] == float(row["fitness"])
        assert behaviour["rotation"] == pytest.approx(float(row["rotation"]))
        assert behaviour["mean_cluster_size"] == pytest.approx(float(row["mean_cluster_size"]))
        assert behaviour_class(behaviour) == row["class"]
        motion = sm.classify_motion(float(row["rotation"]))
        assert row["class"].startswith(motion)
    summary = schema.read(tmp_path / "run", QDSummary)
    assert summary is not None and summary.done and summary.evaluations == 12
    assert summary.cells == len(rows)
    assert set(summary.classes) == {r["class"] for r in rows}
    for name, elite in summary.classes.items():
        assert elite.fitness == max(float(r["fitness"]) for r in rows if r["class"] == name)


def test_sim_map_elites_writes_the_archive_figures_and_post_evaluated_elites(tmp_path, capsys):
    config = tmp_path / "qd.yaml"
    config.write_text(
        yaml.safe_dump({**TINY, "optimizer": {**TINY["optimizer"], "name": "one-plus-one"}})
    )
    out = tmp_path / "run"
    args = ["--config", str(config), "--optimizer", "map-elites", "--out", str(out), "--seed", "2"]
    code = main(["sim", *args])
    assert code == 0
    printed = capsys.readouterr().out
    assert "MAP-Elites in basic" in printed and "elites (coverage" in printed
    for name in (ARCHIVE, QD_PROGRESS, "plots/qd_heatmap.png", "plots/qd_progress.png"):
        assert (out / name).stat().st_size > 0, name
    progress = _rows(out / QD_PROGRESS)
    assert [int(r["evaluations"]) for r in progress] == [4, 8, 12]
    coverage = [float(r["coverage"]) for r in progress]
    assert coverage == sorted(coverage) and coverage[-1] > 0
    summary = schema.read(out, QDSummary)
    assert summary is not None and summary.classes
    for name, elite in summary.classes.items():
        assert elite.directory is not None and elite.post_class is not None
        post = schema.read(out / elite.directory, PostEvaluation)
        assert post is not None, name
        assert elite.post_fitness == pytest.approx(post.swarm_fitness)
        assert f"{name}: best elite {elite.fitness:.4f}" in printed
    # Done: resume has nothing left to do.
    assert main(["resume", str(out)]) == 0
    assert "is complete" in capsys.readouterr().out
    # The report draws the figures again and says what the run found.
    (out / "plots" / "qd_heatmap.png").unlink()
    assert main(["report", str(out)]) == 0
    printed = capsys.readouterr().out
    assert (out / "plots" / "qd_heatmap.png").stat().st_size > 0
    assert all(f"{name}: best elite" in printed for name in summary.classes)
    # status tells where a MAP-Elites run stands, as it does for a (1+1) run.
    assert main(["status", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "MAP-Elites" in printed and "phase: done, 12/12 evaluations" in printed
    assert f"{summary.cells} cells filled" in printed
    assert all(f"{name}: best elite" in printed for name in summary.classes)


def test_a_stopped_run_resumes_to_the_result_it_would_have_had(tmp_path):
    whole = QDRun(_experiment(seed=9)).run(tmp_path / "whole", plots=False)
    asked = []

    def stop_after_two_batches() -> bool:
        asked.append(1)
        return len(asked) == 3

    stopped = QDRun(_experiment(seed=9)).run(
        tmp_path / "split", plots=False, should_stop=stop_after_two_batches
    )
    assert stopped is None
    progress = (
        _rows(tmp_path / "split" / QD_PROGRESS)
        if (tmp_path / "split" / QD_PROGRESS).exists()
        else []
    )
    assert progress == []  # the tables are written at the end
    resumed = QDRun(_experiment(seed=9)).run(tmp_path / "split", plots=False, resume=True)
    assert whole is not None and resumed is not None
    for name in (ARCHIVE, QD_PROGRESS):
        assert (tmp_path / "whole" / name).read_text() == (tmp_path / "split" / name).read_text()
    # The same elites, post-evaluated alike.
    assert whole.summary.classes == resumed.summary.classes
    # Killed before its first checkpoint (only qd.json there): resumed, it starts afresh.
    (tmp_path / "early").mkdir()
    (tmp_path / "early" / QDSummary.FILE).write_bytes(
        (tmp_path / "whole" / QDSummary.FILE).read_bytes()
    )
    early = QDRun(_experiment(seed=9)).run(tmp_path / "early", plots=False, resume=True)
    assert early is not None
    assert (tmp_path / "early" / ARCHIVE).read_text() == (tmp_path / "whole" / ARCHIVE).read_text()


def test_object_manipulation_files_elites_by_d_r_and_d_b_in_the_paper_classes(tmp_path):
    measures = [_axis("distance_covered", 0.0, 1.0, 5), _axis("box_displacement", 0.0, 0.5, 5)]
    experiment = _experiment(
        scenario="boxes", evolution={"evaluations": 8},
        optimizer={"name": "map-elites", "batch": 4, "measures": measures},
    )  # fmt: skip
    result = QDRun(experiment).run(tmp_path / "run", plots=False, post_evaluate=False)
    assert result is not None
    rows = _rows(tmp_path / "run" / ARCHIVE)
    assert rows and {r["class"] for r in rows} <= {"pushing", "reverse driving", "circling"}
    for row in rows:
        d_b = float(row["box_displacement"])
        assert float(row["grid.box_displacement"]) == d_b
        assert (row["class"] == "pushing") == (d_b > sm.PUSHING_ABOVE)


def test_a_qd_study_task_runs_and_summarises_its_classes(tmp_path):
    from studies.tasks import SUMMARY, check_task, run_dir, run_task

    params = {k: v for k, v in TINY.items() if k != "setting"} | {"setting": "paper"}
    task = {"group": "qd", "kind": "qd", "seed": 3, "sweep": {}, "run": "qd/seed-3"}
    task["params"] = params
    check_task(task)
    summary = run_task(task, str(tmp_path))
    assert summary["status"] == "done", summary.get("error")
    assert summary["evaluations"] == 12 and summary["cells"] >= 1
    assert summary["classes"] and summary["best_fitness"] == max(
        c["fitness"] for c in summary["classes"].values()
    )
    assert (run_dir(tmp_path, task) / SUMMARY).is_file()
    optimizer = {"name": "map-elites", "measures": [_axis("box_displacement")]}
    bad = {**task, "params": {**params, "optimizer": optimizer}}
    with pytest.raises(ConfigError, match="d_B needs boxes"):
        check_task(bad)
