"""Study files: validated with errors naming file and key; expanded into one task per run."""

from __future__ import annotations

import pytest
from study_helpers import TINY_RUNS, write_study

from minimize_surprise.errors import ConfigError
from studies.spec import expand, load_study, run_name


def test_a_study_expands_into_one_task_per_group_sweep_value_and_seed(tmp_path):
    study = load_study(write_study(tmp_path))
    tasks = expand(study)
    assert len(tasks) == TINY_RUNS
    first = tasks[0]
    assert first["group"] == "evolved" and first["kind"] == "evolved" and first["seed"] == 1
    assert first["sweep"] == {"simulation.arena_side": 0.8}
    # Defaults under the group's params, the sweep value set deep.
    assert first["params"]["setting"] == "lab" and first["params"]["scenario"] == "basic"
    assert first["params"]["simulation"] == {"arena_side": 0.8}
    assert first["run"] == "evolved/arena_side=0.8/seed-1"
    assert len({t["run"] for t in tasks}) == TINY_RUNS


@pytest.mark.parametrize(
    ("text", "key", "words"),
    [
        ("name: x\ngroups: []\n", "groups", "at least one group"),
        ("name: x\ngroups: [{name: a, kind: evolved, seeds: 0}]\n", "groups[0].seeds", ""),
        ("name: x\ngroups: [{name: a, kind: flying}]\n", "groups[0].kind", "unknown run kind"),
        ("name: x\ngroups: [{name: a, kind: random, colour: red}]\n", "groups[0].colour", ""),
        (
            "name: x\ngroups: [{name: a, kind: random, sweep: {robots: []}}]\n",
            "groups[0].sweep.robots",
            "at least one value",
        ),
        (
            "name: x\ngroups: [{name: a, kind: random}, {name: a, kind: evolved}]\n",
            "groups",
            "used twice",
        ),
        ("name: x\ngroups: [{name: a, kind: random, seeds: {from: 5, to: 2}}]\n", "", "from"),
        (
            "name: x\ngroups:\n"
            "  - {name: a, kind: evolved, params: {evolution: {evaluations: null}}}\n",
            "groups[0].params.evolution.evaluations",
            "an endless run never ends",
        ),
    ],
)
def test_a_bad_study_names_the_file_and_key(tmp_path, text, key, words):
    path = write_study(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_study(path)
    assert info.value.file == str(path)
    if key:
        assert info.value.key == key
    assert words in str(info.value)


def test_seed_forms(tmp_path):
    text = (
        "name: s\ngroups:\n"
        "  - {name: a, kind: random, seeds: 3}\n"
        "  - {name: b, kind: random, seeds: {from: 5, to: 6}}\n"
        "  - {name: c, kind: random, seeds: [9, 4]}\n"
    )
    tasks = expand(load_study(write_study(tmp_path, text)))
    assert [(t["group"], t["seed"]) for t in tasks] == [
        ("a", 1), ("a", 2), ("a", 3), ("b", 5), ("b", 6), ("c", 9), ("c", 4),
    ]  # fmt: skip


def test_run_names_are_safe_paths():
    assert run_name("g", {"simulation.arena_side": 0.7, "robots": 4}, 3) == (
        "g/arena_side=0.7,robots=4/seed-3"
    )
    assert run_name("g", {"x": "a/b c"}, 1) == "g/x=a_b_c/seed-1"


def test_the_shipped_paper_studies_load_and_expand():
    from studies.runner import find_study, shipped_studies

    shipped = shipped_studies()
    full = expand(load_study(shipped["paper-sec5"]))
    # basic at five arena sides, boxes and gradient; 20 evolved runs and 20 random pairs each
    assert len(full) == 5 * 40 + 40 + 40
    groups = {t["group"] for t in full}
    assert groups == {
        f"{s}-{k}" for s in ("basic", "boxes", "gradient") for k in ("evolved", "random")
    }
    sides = {t["params"]["simulation"]["arena_side"] for t in full if t["group"] == "basic-evolved"}
    assert sides == {0.7, 0.8, 0.9, 1.0, 1.5}
    assert all(t["params"]["setting"] == "paper" for t in full)
    reduced = expand(load_study(find_study("paper-sec5-reduced")))
    assert len(reduced) == 5 + 10 + 5 + 10
    # The scale study keeps the basic arena's density (10 robots per square metre of carpet).
    scale = expand(load_study(find_study("scale")))
    assert len(scale) == 2 * (5 + 5 + 3)
    sizes = {(t["params"]["robots"], t["params"]["simulation"]["arena_side"]) for t in scale}
    assert {n for n, _ in sizes} == {10, 100, 1000}
    assert all(n / side**2 == pytest.approx(10, rel=1e-4) for n, side in sizes)
