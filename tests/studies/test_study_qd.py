"""A study's MAP-Elites runs beside its evolved runs: the classes each found and the per-class
fitness comparison of its report (studies.qd_tables)."""

from __future__ import annotations

import pandas as pd
import pytest

from studies.qd_tables import qd_comparison, qd_markdown


def _frame() -> pd.DataFrame:
    def evolved(seed, fitness, behaviour, side=1.0):
        return {"group": "e", "kind": "evolved", "seed": seed, "scenario": "basic",
                "setting": "paper", "arena_side": side, "best_fitness": fitness,
                "behaviour": behaviour, "_summary": {}}  # fmt: skip

    classes = {
        name: {"fitness": fitness, "post_fitness": fitness + 0.01, "post_class": name}
        for name, fitness in [
            ("stopped/grouped", 0.90), ("stopped/dispersed", 0.85), ("circling/dispersed", 0.80)
        ]
    }  # fmt: skip
    qd = {"group": "q", "kind": "qd", "seed": 1, "scenario": "basic", "setting": "paper",
          "arena_side": 1.0, "best_fitness": 0.9, "behaviour": None,
          "_summary": {"classes": classes}}  # fmt: skip
    rows = [evolved(1, 0.93, "stopped/grouped"), evolved(2, 0.91, "stopped/grouped"),
            evolved(3, 0.86, "stopped/dispersed"),
            evolved(4, 0.99, "circling/grouped", side=1.5), qd]  # fmt: skip
    frame = pd.DataFrame(rows)
    frame.attrs["sweep"] = ["arena_side"]
    return frame


def test_each_class_puts_the_best_elite_beside_the_runs_median_of_its_condition():
    rows = {r["class"]: r for r in qd_comparison(_frame())}
    # The 1.5 m run is another condition: its class is not among the peers'.
    assert set(rows) == {"stopped/grouped", "stopped/dispersed", "circling/dispersed"}
    grouped = rows["stopped/grouped"]
    assert grouped["runs"] == 2 and grouped["runs_median_best_fitness"] == 0.92
    assert round(grouped["difference"], 6) == -0.02 and grouped["within_tolerance"]
    assert round(rows["stopped/dispersed"]["difference"], 6) == -0.01
    assert (
        rows["circling/dispersed"]["runs"] == 0 and rows["circling/dispersed"]["difference"] is None
    )
    text = qd_markdown(list(rows.values()))
    assert "classes in the archive: 3" in text and "classes of the runs' best genomes: 2" in text
    assert "more classes than the runs: yes" in text


def test_a_study_without_qd_runs_has_no_comparison():
    frame = _frame()
    assert qd_comparison(frame[frame["kind"] != "qd"]) == []


QD_STUDY = """
name: tiny-qd
description: a MAP-Elites run beside three evolved runs of its condition
defaults:
  setting: paper
  scenario: basic
  robots: 4
  evaluation_steps: 60
  post_evaluation_steps: 60
groups:
  - name: evolved
    kind: evolved
    params: {evolution: {evaluations: 4}}
    seeds: 3
    sweep:
      simulation.arena_side: [1.0]
  - name: qd
    kind: qd
    params:
      evolution: {evaluations: 12}
      optimizer: {name: map-elites, batch: 4}
    seeds: 1
    sweep:
      simulation.arena_side: [1.0]
"""


@pytest.mark.slow
def test_a_study_with_a_qd_group_reports_the_comparison(tmp_path):
    from study_helpers import write_study

    from studies.executors import LocalPool
    from studies.report import write_study_report
    from studies.runner import run_study

    pool = LocalPool(1)
    try:
        run_study(write_study(tmp_path, QD_STUDY), tmp_path / "study", pool)
    finally:
        pool.close()
    found = write_study_report(tmp_path / "study")
    table = pd.read_csv(tmp_path / "study" / "report" / "qd.csv")
    assert found["qd"] == len(table) and len(table)
    runs = pd.read_csv(tmp_path / "study" / "report" / "runs.csv")
    evolved = runs[runs["kind"] == "evolved"]
    # Every class of the evolved runs' best genomes has its row, with their count.
    for name, count in evolved["behaviour"].value_counts().items():
        assert int(table.loc[table["class"] == name, "runs"].iloc[0]) == count
    assert (tmp_path / "study" / "report" / "qd.md").read_text().startswith("## qd, seed 1")
