"""Shared helpers of the master's tests: small configurations, scripted swarms, the reference run.

The reference run drives the (1+1) optimizer directly with the scripted robots' deterministic
fitness, with no network at all. Because a failed round repeats the same candidate and draws no
random numbers, every correct run of the master (faults or not, killed and resumed or not) must
produce exactly the reference's rows.
"""

from __future__ import annotations

import asyncio
import csv
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from master_service import Master, MasterConfig, Progress
from master_service.rundir import RunDir
from minimize_surprise.config import EvolutionConfig, ExperimentConfig
from minimize_surprise.evolution import OnePlusOne
from minimize_surprise.fitness import swarm_fitness
from minimize_surprise.network import GenomeLayout, spec_from_config
from minimize_surprise.wire import EvaluationStats
from runfiles import schema
from runfiles.schema import Simulation, evaluation_header, format_row
from standins.scripted_robots import ScriptedRobot, deterministic_fitness

SECRET = b"test-secret"

#: Columns that must agree between runs; ``attempts`` and ``duration_s`` legitimately differ.
COMPARED = ("evaluation", "kind", "fitness", "best_fitness", "accepted")


def experiment(evaluations: int = 12, **overrides: Any) -> ExperimentConfig:
    """A small, fast experiment: 3 robots, 1-step evaluations, a 4-step post-evaluation."""
    values: dict[str, Any] = {
        "robots": 3,
        "evaluation_steps": 1,
        "post_evaluation_steps": 4,
        "seed": 3,
        "evolution": EvolutionConfig(evaluations=evaluations),
    }
    values.update(overrides)
    return ExperimentConfig(**values)


def master_config(exp: ExperimentConfig | None = None, **overrides: Any) -> MasterConfig:
    """A master configuration for loopback tests: any free port, short deadlines."""
    values: dict[str, Any] = {
        "experiment": exp or experiment(),
        "port": 0,
        # A 1-step round's deadline is 0.1 s + this: a time-out costs well under a second.
        "round_margin": 0.3,
        "heartbeat_interval": 0.25,
        "handshake_timeout": 1.0,
    }
    values.update(overrides)
    return MasterConfig(**values)


def robot_ids(n: int) -> list[str]:
    """The ids the helpers give robots: r0, r1, ... (sorted order = index order for n <= 10)."""
    return [f"r{i}" for i in range(n)]


def make_robots(port: int, n: int, **kwargs: Any) -> list[ScriptedRobot]:
    """``n`` scripted robots r0.. with matching indices (not connected yet)."""
    return [
        ScriptedRobot(rid, SECRET, port, index=i, **kwargs) for i, rid in enumerate(robot_ids(n))
    ]


async def connect(robots: list[ScriptedRobot]) -> None:
    """Connect every robot."""
    await asyncio.gather(*(robot.connect() for robot in robots))


async def close(robots: list[ScriptedRobot]) -> None:
    """Close every robot's connection."""
    await asyncio.gather(*(robot.close() for robot in robots))


def read_csv(path: Path) -> list[dict[str, str]]:
    """The rows of an evaluations.csv."""
    with open(path, newline="", encoding="utf-8") as file:
        return list(csv.DictReader(file))


def reference_rows(exp: ExperimentConfig, robots: list[str]) -> list[dict[str, str]]:
    """The rows an uninterrupted run with the scripted robots must write (all columns but
    ``attempts`` and ``duration_s``)."""
    size = GenomeLayout(spec_from_config(exp)).size
    optimizer = OnePlusOne(exp.evolution, size, exp.seed)
    header = evaluation_header(robots, robot_stats=True)
    # The scripted robots keep every deadline, read every sensor and report no battery.
    stats = [EvaluationStats(steps_run=exp.evaluation_steps, overruns=0, interventions={})] * len(
        robots
    )
    rows = []
    # The scripted robots' safety stops every fifth step from the first.
    share = ((exp.evaluation_steps + 4) // 5) / exp.evaluation_steps
    while not optimizer.done:
        genome = optimizer.ask().genome
        fitnesses = [deterministic_fitness(genome, i) for i in range(len(robots))]
        out = optimizer.tell(swarm_fitness(fitnesses))
        line = format_row(
            out.evaluation, out.kind, out.fitness, out.best_fitness, out.accepted, 1, 0.0, share,
            fitnesses, stats,
        )  # fmt: skip
        row = dict(zip(header, line.rstrip("\n").split(","), strict=True))
        rows.append(comparable(row))
    return rows


def comparable(row: dict[str, str]) -> dict[str, str]:
    """A row without the columns that may differ between correct runs."""
    return {k: v for k, v in row.items() if k not in ("attempts", "duration_s")}


def assert_matches_reference(run_dir: Path, exp: ExperimentConfig, robots: list[str]) -> None:
    """evaluations.csv holds exactly the reference rows: none lost, none twice, same values."""
    rows = read_csv(run_dir / "evaluations.csv")
    assert [int(r["evaluation"]) for r in rows] == list(range(1, exp.evolution.evaluations + 1))
    assert [comparable(r) for r in rows] == reference_rows(exp, robots)


class ProgressLog:
    """A progress listener that remembers every update and lets a test wait for a condition."""

    def __init__(self) -> None:
        self.updates: list[Progress] = []
        self._changed = asyncio.Event()

    def __call__(self, progress: Progress) -> None:
        self.updates.append(progress)
        self._changed.set()

    async def wait(self, predicate: Callable[[Progress], bool], timeout: float = 5.0) -> Progress:
        """Wait for an update satisfying ``predicate`` (also among the earlier ones)."""
        async with asyncio.timeout(timeout):
            seen = 0
            while True:
                for progress in self.updates[seen:]:
                    if predicate(progress):
                        return progress
                seen = len(self.updates)
                self._changed.clear()
                await self._changed.wait()


async def run_with(master: Master, robots: list[ScriptedRobot], timeout: float = 15.0) -> Any:
    """Connect ``robots`` and run ``master`` to the end."""
    task = asyncio.create_task(master.run())
    await connect(robots)
    async with asyncio.timeout(timeout):
        return await task


def write_experiment(path: Path, evaluations: int, steps: int) -> Path:
    """An experiment file at ``path`` for a command-line run: the paper's basic scenario with 3
    robots, ``evaluations`` of ``steps`` steps and a short post-evaluation."""
    path.write_text(
        "scenario: basic\nsetting: paper\nrobots: 3\nseed: 3\n"
        f"evaluation_steps: {steps}\npost_evaluation_steps: 50\n"
        f"evolution:\n  evaluations: {evaluations}\n"
    )
    return path


#: The arrays of a robot's post-evaluation trace.
TRACE_ARRAYS = ("sensors", "predictions", "actions", "commands", "safety", "poses")


def run_rows(run: Path, ignore: frozenset[str] | set[str]) -> list[dict[str, str]]:
    """The rows of a run's evaluations.csv without the columns in ``ignore``."""
    return [{k: v for k, v in row.items() if k not in ignore} for row in RunDir(run).read_rows()]


def assert_same_run(a: Path, b: Path, robots: int, ignore: frozenset[str] | set[str]) -> None:
    """Two simulated runs ended alike: every row (but the ``ignore`` columns), every robot's
    post-evaluation trace and the boxes the post-evaluation began with."""
    assert run_rows(a, ignore) == run_rows(b, ignore)
    for robot in [f"sim-{i}" for i in range(robots)]:
        with (
            np.load(a / "traces" / f"{robot}.npz") as x,
            np.load(b / "traces" / f"{robot}.npz") as y,
        ):
            for name in TRACE_ARRAYS:
                assert np.array_equal(x[name], y[name]), (robot, name)
    first, second = schema.read(a, Simulation), schema.read(b, Simulation)
    assert first is not None and second is not None
    assert first.post_evaluation_boxes == second.post_evaluation_boxes
