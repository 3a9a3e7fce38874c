"""A tiny study for the tests: two kinds, a sweep, two seeds; every run well under a second."""

from __future__ import annotations

from pathlib import Path

TINY = """
name: tiny
description: a tiny study for the tests
defaults:
  setting: lab
  robots: 2
  evaluation_steps: 8
  post_evaluation_steps: 12
  evolution: {evaluations: 3}
  plots: false
groups:
  - name: evolved
    kind: evolved
    params: {scenario: basic}
    seeds: 2
    sweep:
      simulation.arena_side: [0.8, 1.0]
  - name: random
    kind: random
    params: {scenario: basic}
    seeds: [1, 2]
    sweep:
      simulation.arena_side: [0.8, 1.0]
"""

#: Runs of TINY.
TINY_RUNS = 8


def write_study(tmp_path: Path, text: str = TINY, name: str = "tiny.yaml") -> Path:
    """The study file ``text`` in ``tmp_path``."""
    path = tmp_path / name
    path.write_text(text)
    return path


#: Columns of runs.csv that depend on where and when a run ran (and with which others), not on
#: what it computed.
VOLATILE = ("seconds", "host", "batch")


def table(out: Path):
    """The study's runs.csv without the volatile columns, in run order (a pandas DataFrame)."""
    import pandas as pd

    from studies.report import write_study_report

    write_study_report(out)
    frame = pd.read_csv(out / "report" / "runs.csv")
    return (
        frame.drop(columns=[c for c in VOLATILE if c in frame])
        .sort_values("run")
        .reset_index(drop=True)
    )
