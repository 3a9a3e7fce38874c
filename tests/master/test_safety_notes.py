"""The report says the safety layer's dominance apart: notes on the evolved behaviour, warnings
for a person to act on (the quick start's held aggregates are notes, a too-light floor a
warning)."""

from __future__ import annotations

import numpy as np

from minimize_surprise.wire import EvaluationStats
from reporting.report import _safety_metrics, safety_lines
from runfiles.schema import PostEvaluation, PostRobot


def _post(reasons: dict[str, int], steps: int) -> PostEvaluation:
    stats = EvaluationStats(steps_run=steps, overruns=0, interventions=reasons)
    robots = {"r0": PostRobot(fitness=0.5, stats=stats)}
    return PostEvaluation(
        evaluation_id=0, steps=steps, genome_fitness=None, swarm_fitness=0.5, robots=robots
    )


def test_the_report_says_notes_and_warnings_apart() -> None:
    rows = [{"safety_share": 1.0}] * 10
    held = _safety_metrics(rows, _post({"front": 80}, 100), {})
    assert held is not None and held["warnings"] == []
    assert [n.split(" the safety")[0] for n in held["notes"]] == [
        "in the post-evaluation",
        "in the last tenth of the evolution",
    ]
    lines = safety_lines({"safety": held})
    assert [line.split(":")[0] for line in lines] == ["safety layer drove", "note", "note"]
    floor = _safety_metrics(rows, _post({"ground": 95}, 100), {})
    assert floor is not None and floor["notes"] == [] and len(floor["warnings"]) == 2
    assert any(line.startswith("warning: ") for line in safety_lines({"safety": floor}))
    # The same counts, from a robot the ground rule held only after it set off: the arena's edge.
    later = {"r0": {"safety": np.array([""] * 5 + ["ground"] * 95)}}
    edge = _safety_metrics(rows, _post({"ground": 95}, 100), later)
    assert edge is not None and edge["warnings"] == [] and len(edge["notes"]) == 2
    at_once = {"r0": {"safety": np.array(["ground"] * 100)}}
    assert len(_safety_metrics(rows, _post({"ground": 95}, 100), at_once)["warnings"]) == 2
