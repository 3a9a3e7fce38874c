"""The report's fitness around each change: drop and recovery on crafted series, and in the
report of a run whose arena changed (table, figure, metrics)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from master_service.experiments.engine_run import FastRun
from master_service.experiments.simulate import simulation_experiment
from reporting.recovery import recoveries, recovery_table
from runfiles.schema import EVENT_ARENA, EVENT_MARK, Event, append_event


def change(evaluation: int, kind: str = EVENT_ARENA, detail: str = "the light moves") -> Event:
    return Event(time=0.0, kind=kind, evaluation=evaluation, detail=detail)


def test_drop_and_recovery_of_a_crafted_series():
    # 20 evaluations at 0.8; the arena changes; 5 at 0.5 (one at 0.4), then back at 0.8.
    series = [0.8] * 20 + [0.5, 0.4, 0.5, 0.5, 0.5] + [0.8] * 15
    (found,) = recoveries(series, [change(20)])
    assert found.level_before == pytest.approx(0.8)
    assert found.lowest_after == pytest.approx(0.4)
    assert found.drop == pytest.approx(0.4)
    # The median of the last 10, all after the change, reaches 0.8 with 6 of them back: 11.
    assert found.recovery == 11


def test_a_series_that_stays_low_is_not_recovered_and_a_mark_counts_like_an_event():
    series = [0.7, 0.8] * 10 + [0.6] * 30
    escape = Event(time=0.0, kind="escape", evaluation_id=3, robot="a")
    found = recoveries(series, [escape, change(20, EVENT_MARK, "moved the light by hand")])
    assert len(found) == 1 and found[0].kind == EVENT_MARK
    assert found[0].level_before == pytest.approx(0.75)
    assert found[0].drop == pytest.approx(0.15) and found[0].recovery is None
    table = recovery_table(found)
    assert "| 20 | moved the light by hand (mark) | 0.7500 | 0.6000 | 0.1500 | not recovered |" in (
        table
    )


def test_a_change_that_makes_the_task_easier_recovers_at_once():
    series = [0.5] * 10 + [0.9] * 10
    (found,) = recoveries(series, [change(10)])
    assert found.drop == pytest.approx(-0.4) and found.recovery == 10


def test_a_change_near_the_ends_uses_what_there_is():
    (found,) = recoveries([0.6, 0.7, 0.2, 0.3], [change(2)])
    assert found.level_before == pytest.approx(0.65) and found.drop == pytest.approx(0.45)
    assert found.recovery is None  # no whole window after it


def test_the_report_of_a_changing_run_has_the_table_and_the_figure(tmp_path: Path):
    config = simulation_experiment(
        data={
            "setting": "paper",
            "scenario": "gradient",
            "robots": 3,
            "seed": 1,
            "evolution": {"evaluations": 30},
            "evaluation_steps": 40,
            "post_evaluation_steps": 40,
            "events": [{"kind": "light-moves", "evaluation": 15, "position": [0.4, 0.4]}],
        }
    )
    run = tmp_path / "run"
    FastRun(config).run(run, plots=False)
    append_event(run, change(25, EVENT_MARK, "a person's mark"))
    from reporting.report import write_report

    metrics = write_report(run, plots=True)
    assert [c["detail"] for c in metrics["recovery"]] == [
        "the light moves to (0.4, 0.4)",
        "a person's mark",
    ]
    assert metrics["recovery"][0]["evaluation"] == 14
    assert (run / "plots" / "recovery.png").stat().st_size > 0
    table = (run / "plots" / "recovery.md").read_text()
    assert "| 14 | the light moves to (0.4, 0.4) |" in table
    assert json.loads((run / "metrics.json").read_text())["recovery"] == metrics["recovery"]
