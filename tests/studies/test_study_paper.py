"""A study file that says what the paper reports for a group gets its runs put beside it:
``report/paper.csv`` and ``paper.md``, one row per condition, with whether our median holds the
paper's bound."""

from __future__ import annotations

import pandas as pd
import pytest
from study_helpers import TINY, write_study

from studies.executors import LocalPool
from studies.report import write_study_report
from studies.runner import run_study

pytestmark = pytest.mark.slow

PAPER = TINY.replace(
    """      simulation.arena_side: [0.8, 1.0]
  - name: random""",
    """      simulation.arena_side: [0.8, 1.0]
    paper:
      median_fitness_at_least: 0.01
      classes: "whatever the paper saw"
      source: "Sec. X"
  - name: random""",
).replace(
    """    seeds: [1, 2]
    sweep:
      simulation.arena_side: [0.8, 1.0]
""",
    """    seeds: [1, 2]
    sweep:
      simulation.arena_side: [0.8, 1.0]
    paper: {median_fitness_at_most: 0.01}
""",
)


def test_the_report_puts_each_condition_beside_the_paper(tmp_path):
    assert PAPER != TINY
    pool = LocalPool(2)
    try:
        run_study(write_study(tmp_path, PAPER), tmp_path / "study", pool)
    finally:
        pool.close()
    write_study_report(tmp_path / "study")
    beside = pd.read_csv(tmp_path / "study" / "report" / "paper.csv")
    assert list(beside["group"]) == ["evolved", "evolved", "random", "random"]
    assert list(beside["condition"]) == ["arena_side=0.8", "arena_side=1.0"] * 2
    assert list(beside["paper_median_fitness"]) == [">= 0.01"] * 2 + ["<= 0.01"] * 2
    # Any swarm's surprise fitness lies well above 0.01: the evolved bound holds, the random not.
    assert list(beside["holds"]) == [True, True, False, False]
    assert (beside["runs"] == 2).all() and beside["classes"].str.len().gt(0).all()
    assert beside["paper_classes"][0] == "whatever the paper saw"
    text = (tmp_path / "study" / "report" / "paper.md").read_text()
    assert text.startswith("| group | condition | runs | median_fitness |")
    assert "| evolved | arena_side=0.8 | 2 |" in text
