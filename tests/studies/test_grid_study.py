"""A tiny grid-world study end to end on local worker processes: evolved, random and selected
random runs over two grid sizes, reruns and damage of the evolved genomes (groups that wait for
the evolved runs with ``after``), the report's tables, tests and Sec. IV figures."""

from __future__ import annotations

import json

import pandas as pd
import pytest
from study_helpers import write_study

from gridworld.tasks import check_params
from minimize_surprise.errors import ConfigError
from studies.executors import LocalPool
from studies.report import write_study_report
from studies.runner import run_study
from studies.spec import expand, load_study, task_stages

pytestmark = pytest.mark.slow

TINY_GRID = """
name: tiny-grid
description: the grid world's study kinds, tiny
defaults: {steps: 20}
groups:
  - name: evolved
    kind: grid-evolved
    params: {agents: 12, repetitions: 2, population: 4, generations: 3}
    seeds: 3
    sweep: {size: [7, 8]}
  - name: random
    kind: grid-random
    params: {agents: 12, repetitions: 2}
    seeds: 3
    sweep: {size: [7, 8]}
  - name: selected
    kind: grid-selected-random
    params: {agents: 12, repetitions: 2, candidates: 12}
    seeds: 3
    sweep: {size: [7, 8]}
  - name: rerun
    kind: grid-rerun
    after: [evolved]
    params: {agents: 12, genome_run: "evolved/size=7/seed-{seed}"}
    seeds: 3
    sweep: {size: [7, 9]}
  - name: damage
    kind: grid-damage
    after: [evolved]
    params: {genome_run: evolved/size=8/seed-1, variant: reposition, xmax: 2, ymax: 2}
    seeds: 2
"""


def test_groups_that_use_other_runs_wait_for_them(tmp_path):
    study = load_study(write_study(tmp_path, TINY_GRID))
    assert study.stages() == [["evolved", "random", "selected"], ["rerun", "damage"]]
    tasks = expand(study)
    stages = task_stages(tasks)
    assert [sorted({t["group"] for t in stage}) for stage in stages] == [
        ["evolved", "random", "selected"],
        ["damage", "rerun"],
    ]
    # Once the evolved runs have all finished (none pending), the reruns wait for nothing.
    pending = [t for t in tasks if t["group"] != "evolved"]
    assert len(task_stages(pending)) == 1


@pytest.mark.parametrize(
    ("groups", "key", "message"),
    [
        ("  - {name: a, kind: grid-random, after: [b]}\n", "groups[0].after", "no group"),
        (
            "  - {name: a, kind: grid-random, after: [b]}\n"
            "  - {name: b, kind: grid-random, after: [a]}\n",
            "groups",
            "wait for each other",
        ),
    ],
)
def test_after_names_groups_that_exist_and_no_circle(tmp_path, groups, key, message):
    path = write_study(tmp_path, "name: bad\ngroups:\n" + groups)
    with pytest.raises(ConfigError, match=message) as caught:
        load_study(path)
    assert caught.value.key == key and caught.value.file == str(path)


def test_a_tiny_grid_study_from_runs_to_figures(tmp_path):
    out = tmp_path / "study"
    pool = LocalPool(2)
    try:
        counts = run_study(write_study(tmp_path, TINY_GRID), out, pool)
    finally:
        pool.close()
    assert (counts.done, counts.failed) == (6 + 6 + 6 + 6 + 2, 0), counts.failures
    # A rerun ran the evolved genome of its own seed, bit for bit.
    for seed in (1, 2, 3):
        evolved = json.loads(
            (out / f"runs/evolved/size=7/seed-{seed}/best_genome.json").read_text()
        )
        rerun = json.loads((out / f"runs/rerun/size=9/seed-{seed}/best_genome.json").read_text())
        assert rerun["genome"] == evolved["genome"]
    damage = json.loads((out / "runs/damage/seed-1/summary.json").read_text())
    assert 0.0 <= damage["similarity"] <= 1.0 and damage["variant"] == "reposition"

    result = write_study_report(out)
    report = out / "report"
    # The grid runs clustered by their pattern scores beside the hand-set patterns.
    assert "grid" in result["clusters"] and (report / "clusters.md").is_file()
    assert set(pd.read_csv(report / "clusters.csv")["family"]) == {"grid"}
    runs = pd.read_csv(report / "runs.csv")
    assert len(runs) == 26 and set(runs["status"]) == {"done"}
    assert {"pattern", "quality", "size"} <= set(runs.columns)
    summary = pd.read_csv(report / "summary.csv")
    evolved7 = summary[(summary["group"] == "evolved") & (summary["size"] == 7)].iloc[0]
    fitness = runs[(runs["group"] == "evolved") & (runs["size"] == 7)]["best_fitness"]
    assert evolved7["runs"] == 3 and evolved7["median_fitness"] == pytest.approx(fitness.median())
    statistics = pd.read_csv(report / "statistics.csv")
    # Every two groups of one grid size: fitness and quality (Mann-Whitney U), patterns (Fisher).
    at7 = statistics[statistics["condition"] == "size=7"]
    pairs = {"evolved vs random", "evolved vs selected", "random vs selected", "evolved vs rerun",
             "random vs rerun", "selected vs rerun"}  # fmt: skip
    assert set(at7[at7["measure"] == "best_fitness"]["samples"]) == pairs
    assert set(at7[at7["measure"] == "quality"]["samples"]) == pairs
    assert set(at7[at7["test"] == "fisher-exact"]["samples"]) == pairs
    kw = statistics[statistics["test"] == "kruskal-wallis"]
    assert "evolved across size" in set(kw["condition"])
    assert (statistics["p_bonferroni"] >= statistics["p"]).all()
    figures = {p.split("/figures/")[1] for p in result["figures"]}
    for name in (
        "grid/fitness_evolved_size=7.png",
        "grid/fitness_quality_by_size.pdf",
        "grid/patterns_evolved_by_size.png",
        "grid/patterns_selected_by_size.png",
        "grid/predictions_by_pattern.png",
        "grid/example_grids.png",
    ):
        assert name in figures
        assert (report / "figures" / name).stat().st_size > 0
    assert (report / "evaluations.parquet").is_file()


TINY_QD = """
name: tiny-qd
description: MAP-Elites beside GA runs, tiny
defaults: {size: 8, agents: 16, repetitions: 2, steps: 20, population: 4}
groups:
  - name: evolved
    kind: grid-evolved
    params: {generations: 3}
    seeds: 2
  - name: map-elites
    kind: grid-qd
    params: {generations: 6, measures: [{name: LN, bins: 3}, {name: RD, bins: 3}]}
    seeds: 1
"""


def test_a_map_elites_group_beside_ga_runs_reports_the_patterns_each_found(tmp_path):
    out = tmp_path / "study"
    pool = LocalPool(2)
    try:
        counts = run_study(write_study(tmp_path, TINY_QD), out, pool)
    finally:
        pool.close()
    assert (counts.done, counts.failed) == (3, 0), counts.failures
    qd = json.loads((out / "runs/map-elites/seed-1/summary.json").read_text())
    assert qd["kind"] == "grid-qd" and qd["evaluations"] == 24
    assert (out / "runs/map-elites/seed-1/archive.csv").is_file()
    result = write_study_report(out)
    found = pd.read_csv(out / "report/figures/grid/patterns_found.csv")
    assert list(found["group"]) == ["evolved", "map-elites"]
    assert list(found["runs"]) == [2, 1]
    assert found["count"].iloc[1] == qd["pattern_count"] == len(qd["patterns_found"])
    evolved = {json.loads((out / f"runs/evolved/seed-{s}/summary.json").read_text())["pattern"]
               for s in (1, 2)}  # fmt: skip
    assert found["count"].iloc[0] == len(evolved)
    assert any(p.endswith("grid/patterns_found.png") for p in result["figures"])
    runs = pd.read_csv(out / "report/runs.csv")
    assert set(runs["kind"]) == {"grid-evolved", "grid-qd"} and set(runs["status"]) == {"done"}


def test_a_bad_parameter_fails_the_study_before_any_run(tmp_path):
    path = write_study(
        tmp_path,
        "name: bad\ngroups:\n"
        "  - {name: ok, kind: grid-random, params: {size: 10}}\n"
        "  - {name: damage, kind: grid-damage, params: {agents: 50}, sweep: {size: [9, 10]}}\n",
    )
    with pytest.raises(ConfigError) as caught:
        load_study(path)
    error = caught.value
    assert (error.file, error.key) == (str(path), "groups[1].params.agents")
    assert "size=9" in error.reason


def test_the_shipped_grid_studies_are_the_papers():
    from studies.runner import shipped_studies

    shipped = shipped_studies()
    main = expand(load_study(shipped["paper-sec4"]))
    by_group: dict[str, list[dict]] = {}
    for task in main:
        by_group.setdefault(task["group"], []).append(task)
    # 50 runs per L for L = 11..30 of each kind; the reruns of the L = 16 genomes on every L.
    for group in ("evolved", "random", "selected-random", "rerun-from-16"):
        assert len(by_group[group]) == 20 * 50
        assert {t["sweep"]["size"] for t in by_group[group]} == set(range(11, 31))
    assert {t["params"]["candidates"] for t in by_group["selected-random"]} == {5000}
    rerun = by_group["rerun-from-16"][0]
    assert rerun["after"] == ["evolved"]
    assert rerun["params"]["genome_run"].format(seed=7) == "evolved/size=16/seed-7"
    assert {t["run"] for t in by_group["evolved"]} >= {"evolved/size=16/seed-7"}
    counts = {name: len(expand(load_study(shipped[name]))) for name in shipped}
    assert counts["paper-sec4-novelty"] == 2 * 2 * 50
    assert counts["paper-sec4-noise"] == 2 * 4 * 20
    assert counts["paper-sec4-predefined"] == 6 * 50
    assert counts["paper-sec4-damage"] == 1 + 1 + 20
    assert counts["paper-sec4-reduced"] == 5 * 10
    # One MAP-Elites run with the budget of the 50 GA runs it is compared with, on L = 15.
    qd = {t["group"]: t for t in expand(load_study(shipped["qd-grid"]))}
    assert counts["qd-grid"] == 51 and qd["map-elites"]["kind"] == "grid-qd"
    ga = check_params("grid-evolved", qd["evolved"]["params"])
    me = check_params("grid-qd", qd["map-elites"]["params"])
    assert me.population * me.generations == 50 * ga.population * ga.generations
    assert me.size == ga.size == 15
