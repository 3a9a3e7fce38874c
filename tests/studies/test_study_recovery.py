"""A study whose arena changes: each run's summary keeps its fitness around the change, and the
study's report gives the drop and recovery across seeds per group (report/recovery.md)."""

from __future__ import annotations

import pandas as pd
import pytest
from study_helpers import write_study

from studies.cli import main
from studies.report import write_study_report
from studies.runner import shipped_studies
from studies.spec import expand, load_study

pytestmark = pytest.mark.slow

CHANGING = """
name: changing
description: the light moves at evaluation 8 of 14
defaults:
  setting: paper
  scenario: gradient
  robots: 3
  evaluation_steps: 30
  post_evaluation_steps: 20
  evolution: {evaluations: 14}
groups:
  - name: moves
    kind: evolved
    params:
      events: [{kind: light-moves, evaluation: 8, position: [0.4, 0.4]}]
    seeds: 3
  - name: still
    kind: evolved
    params: {}
    seeds: 1
"""


def test_the_study_report_gives_drop_and_recovery_across_seeds(tmp_path):
    out = tmp_path / "out"
    assert main(["run", str(write_study(tmp_path, CHANGING)), "--out", str(out)]) == 0
    found = write_study_report(out)
    (row,) = found["recovery"]  # the group without events has no change
    assert row["group"] == "moves" and row["runs"] == 3 and row["evaluation"] == 7
    assert row["detail"] == "the light moves to (0.4, 0.4)"
    drops = []
    for seed in (1, 2, 3):
        summary = pd.read_json(out / "runs" / f"moves/seed-{seed}" / "summary.json", typ="series")
        (change,) = summary["recovery"]
        drops.append(change["drop"])
    assert row["median_drop"] == pytest.approx(sorted(drops)[1])
    table = (out / "report" / "recovery.md").read_text()
    assert "| moves | 7 | the light moves to (0.4, 0.4) | 3 |" in table
    csv = pd.read_csv(out / "report" / "recovery.csv")
    assert list(csv["group"]) == ["moves"]


def test_the_shipped_changing_arena_study_loads_and_expands():
    tasks = expand(load_study(shipped_studies()["changing-arena"]))
    assert len(tasks) == 32
    groups = {t["group"]: t["params"]["events"] for t in tasks}
    assert groups["light-control"][0]["position"] == [0.0, 0.0]
    assert {e[0]["kind"] for e in groups.values()} == {
        "light-moves",
        "wall-appears",
        "robots-leave",
    }
