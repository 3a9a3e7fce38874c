"""The engine and the real agents over TCP give the same run for the same seed, bit for bit:
every row of evaluations.csv (but the time it took) and every post-evaluation trace."""

from __future__ import annotations

import asyncio
from pathlib import Path

import msgspec
import numpy as np
import pytest

from master_service.experiments.engine_run import FastRun
from master_service.experiments.simulate import SimulatedSwarm, simulation_experiment
from master_service.rundir import RunDir
from runfiles import schema
from runfiles.schema import ROBOT_STAT_PREFIXES, BestGenome, PostEvaluation, Simulation

TRACE_ARRAYS = ("sensors", "predictions", "actions", "commands", "safety", "poses")


def experiment(tmp_path: Path, scenario: str, **overrides):
    lines = [f"scenario: {scenario}", "setting: paper", "seed: 4"]
    lines += [f"{key}: {value}" for key, value in overrides.items()]
    path = tmp_path / f"{scenario}.yaml"
    path.write_text("\n".join(lines) + "\n")
    return simulation_experiment(config_file=path)


def rows(run: Path) -> list[dict[str, str]]:
    return [{k: v for k, v in row.items() if k != "duration_s"} for row in RunDir(run).read_rows()]


def finder(table: list[dict[str, str]]) -> int:
    """The evaluation that found the best genome: the last accepted one not a re-evaluation."""
    return max(
        int(row["evaluation"])
        for row in table
        if row["accepted"] == "true" and row["kind"] != "reevaluation"
    )


@pytest.mark.slow
@pytest.mark.parametrize(
    ("scenario", "overrides"),
    [
        ("basic", {"robots": 4, "evaluation_steps": 40, "post_evaluation_steps": 60}),
        ("boxes", {"robots": 2, "evaluation_steps": 60, "post_evaluation_steps": 80}),
    ],
)
def test_engine_and_agents_give_the_same_run(tmp_path: Path, scenario: str, overrides):
    config = experiment(tmp_path, scenario, **overrides)
    config = msgspec.structs.replace(
        config, evolution=msgspec.structs.replace(config.evolution, evaluations=12)
    )
    fast = tmp_path / "fast"
    agents = tmp_path / "agents"
    FastRun(config).run(fast)
    asyncio.run(SimulatedSwarm(config).run(agents))

    fast_rows, agent_rows = rows(fast), rows(agents)
    assert len(fast_rows) == 12
    # The agents add what robots report and the engine has not: no overrun, no failed read, no
    # battery.
    stats = [
        {k: row.pop(k) for k in list(row) if k.startswith(ROBOT_STAT_PREFIXES)}
        for row in agent_rows
    ]
    assert all(len(s) == 3 * config.robots and set(s.values()) <= {"", "0"} for s in stats)
    assert fast_rows == agent_rows
    best = schema.read(fast, BestGenome)
    assert best is not None and best == schema.read(agents, BestGenome)
    assert best.evaluation == finder(fast_rows), fast_rows
    for robot in [f"sim-{i}" for i in range(config.robots)]:
        a = np.load(fast / "traces" / f"{robot}.npz")
        b = np.load(agents / "traces" / f"{robot}.npz")
        for name in TRACE_ARRAYS:
            assert np.array_equal(a[name], b[name]), (robot, name)
    post_fast = schema.read(fast, PostEvaluation)
    post_agents = schema.read(agents, PostEvaluation)
    assert post_fast is not None and post_agents is not None
    assert post_fast.swarm_fitness == post_agents.swarm_fitness
    for robot, entry in post_fast.robots.items():
        assert entry.fitness == post_agents.robots[robot].fitness
        other = post_agents.robots[robot]
        assert entry.stats.interventions == other.stats.interventions
    sim_fast = schema.read(fast, Simulation)
    sim_agents = schema.read(agents, Simulation)
    assert sim_fast is not None and sim_agents is not None
    assert sim_fast.post_evaluation_boxes == sim_agents.post_evaluation_boxes
    if scenario == "boxes":
        # The boxes' track, which the report's animation draws, is the same too.
        with np.load(fast / "box_track.npz") as a, np.load(agents / "box_track.npz") as b:
            assert sim_fast.post_evaluation_boxes is not None
            boxes = len(sim_fast.post_evaluation_boxes.start)
            # 80 steps of 0.01 s: a frame every 10 steps (0.1 s) from the first.
            assert a["positions"].shape == (8, boxes, 2)
            assert np.allclose(a["positions"][0], sim_fast.post_evaluation_boxes.start)
            assert np.array_equal(a["positions"], b["positions"])
            assert int(a["every"]) == int(b["every"]) == 10
