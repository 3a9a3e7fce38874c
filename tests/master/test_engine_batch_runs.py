"""Runs evolved together (their swarms evaluated in one compiled call) end exactly as each does
alone: every row of evaluations.csv, every post-evaluation trace, the best genome and the boxes.
"""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest
from master_helpers import assert_same_run, run_rows

from master_service.experiments import engine_run
from master_service.experiments.engine_run import FastRun, run_batch
from master_service.experiments.simulate import simulation_experiment
from master_service.rundir import RunDir
from simulator.engine import evaluate_swarms

#: The wall clock's columns: a batch's time is shared among its runs.
TIMING_COLUMNS = {"duration_s"}


def small(scenario: str, seed: int, evaluations: int, side: float | None = None):
    experiment = simulation_experiment(scenario, setting="paper", robots=3, seed=seed, arena=side)
    return msgspec.structs.replace(
        experiment,
        evolution=msgspec.structs.replace(experiment.evolution, evaluations=evaluations),
        evaluation_steps=50,
        post_evaluation_steps=70,
    )


def assert_same_batched_run(a: Path, b: Path, robots: int) -> None:
    assert_same_run(a, b, robots, TIMING_COLUMNS)
    assert len(run_rows(a, TIMING_COLUMNS)) > 0
    best = [RunDir(p).read_checkpoint().optimizer["best"] for p in (a, b)]  # type: ignore[union-attr]
    assert best[0] == best[1] and best[0] is not None


@pytest.mark.parametrize("scenario", ["basic", "boxes"])
def test_runs_evolved_together_end_as_each_alone(tmp_path: Path, scenario: str, monkeypatch):
    # Three seeds (one in a larger arena) with different numbers of evaluations, so one run ends
    # while the others go on and the batch shrinks.
    experiments = [
        small(scenario, 1, 12),
        small(scenario, 2, 20, side=1.2 if scenario == "basic" else None),
        small(scenario, 3, 16),
    ]
    alone = [tmp_path / f"alone-{i}" for i in range(3)]
    for experiment, run in zip(experiments, alone, strict=True):
        FastRun(experiment).run(run, plots=False)
    together = [tmp_path / f"together-{i}" for i in range(3)]
    sizes = []

    def counted(swarms, genomes, steps, *, record=False):
        sizes.append(len(swarms))
        return evaluate_swarms(swarms, genomes, steps, record=record)

    monkeypatch.setattr(engine_run, "evaluate_swarms", counted)
    outcomes = run_batch(
        [(FastRun(e), run) for e, run in zip(experiments, together, strict=True)], plots=False
    )
    for outcome, a, b in zip(outcomes, alone, together, strict=True):
        assert not isinstance(outcome, BaseException), outcome
        assert outcome.summary.run_dir == b
        assert_same_batched_run(a, b, robots=3)
    # Evaluated together: three at a time until the first run ends, two until the second; the
    # post-evaluations of runs ending at different times alone.
    assert sizes.count(3) >= 12 and sizes.count(2) >= 3 and max(sizes) == 3


def test_a_run_that_cannot_start_leaves_the_others_running(tmp_path: Path):
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "notes.txt").write_text("not an empty directory\n")
    experiments = [small("basic", 1, 6), small("basic", 2, 6)]
    outcomes = run_batch(
        [(FastRun(experiments[0]), tmp_path / "taken"), (FastRun(experiments[1]), tmp_path / "b")]
    )
    assert isinstance(outcomes[0], BaseException)
    assert not isinstance(outcomes[1], BaseException)
    assert len(RunDir(tmp_path / "b").read_rows()) == 6
