"""``surprise-master baseline``: random actor-predictor pairs in the same arena (the paper's
comparison for evolved pairs, Sec. V-B).

Each random pair (a genome drawn as evolution draws its initial genome) runs on every robot of a
freshly reset arena for the post-evaluation length, through the same robot code as an evolved
genome (:class:`robot_agent.runner.EvaluationRunner`: network, safety layer, scoring). Its
``fitness`` is the swarm fitness over the first ``evaluation_steps`` steps, which is what an
evolved genome's fitness measures; the behaviour metrics cover the whole run, like the
post-evaluation of an evolved genome. ``baseline.json`` holds one entry per pair and the median.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from master_service.rundir import write_atomic
from master_service.simulate import simulated_loop, simulated_safety, world_config
from robot_agent.runner import EvaluationRunner
from sim_stub import metrics as sim_metrics
from sim_stub.body import SimSwarm
from sim_stub.world import World
from surprise.config import ExperimentConfig
from surprise.evolution import random_genome
from surprise.fitness import surprise_fitness, swarm_fitness
from surprise.network import GenomeLayout, spec_from_config
from surprise.wire import Evaluate, Result, genome_to_bytes

__all__ = ["BASELINE_FILE", "load_baseline", "run_baseline"]

#: The baseline's results in its output directory.
BASELINE_FILE = "baseline.json"


async def _evaluate_pair(runners: list[EvaluationRunner], msg: Evaluate) -> list[Result]:
    results = await asyncio.gather(*(runner.run(msg) for runner in runners))
    failed = [r for r in results if not isinstance(r, Result)]
    if failed:
        # Nothing can fail in a simulated arena unless the code is broken: say so loudly.
        raise RuntimeError(f"a random pair could not be evaluated: {failed[0]}")
    return list(results)  # type: ignore[arg-type]


def _pair_entry(
    index: int, seed: int, results: list[Result], evaluation_steps: int, boxes: dict[str, Any]
) -> dict[str, Any]:
    fitnesses = []
    poses = []
    for result in results:
        trace = result.trace
        assert trace is not None and trace.poses is not None
        steps = min(evaluation_steps, trace.steps)
        predictions, sensors = trace.array("predictions"), trace.array("sensors")
        fitnesses.append(surprise_fitness(predictions[:steps], sensors[:steps]))
        poses.append(trace.array("poses"))
    length = min(len(p) for p in poses)
    stacked = np.stack([p[:length] for p in poses], axis=1)
    behaviour = sim_metrics.behaviour_metrics(stacked, boxes.get("start"), boxes.get("end"))
    return {
        "pair": index,
        "arena_seed": seed,
        "fitness": swarm_fitness(fitnesses),
        "post_fitness": swarm_fitness([r.fitness for r in results]),
        "robot_fitness": fitnesses,
        "behaviour": msgspec.to_builtins(behaviour),
    }


async def run_baseline(experiment: ExperimentConfig, pairs: int, out: str | Path) -> dict[str, Any]:
    """Evaluate ``pairs`` random network pairs; write and return ``baseline.json``'s content.

    Pair ``k`` uses the genome generator seeded with ``experiment.seed`` and the arena seed
    ``experiment.seed + 1 + k``, so a baseline repeats exactly.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    spec = spec_from_config(experiment)
    size = GenomeLayout(spec).size
    rng = np.random.default_rng(experiment.seed)
    steps = max(experiment.post_evaluation_steps, experiment.evaluation_steps)
    world = World(world_config(experiment), seed=experiment.seed)
    swarm = SimSwarm(world, attach_all=True)
    safety = simulated_safety(experiment)
    entries = []
    async with contextlib.AsyncExitStack() as stack:
        bodies = [await stack.enter_async_context(swarm.body(i)) for i in range(experiment.robots)]
        runners = [
            EvaluationRunner(
                body, body.clock, loop=simulated_loop(experiment), safety=safety, safety_seed=i
            )
            for i, body in enumerate(bodies)
        ]
        for k in range(pairs):
            genome = random_genome(rng, size, experiment.evolution.initial_range)
            seed = experiment.seed + 1 + k
            world.reset(seed=seed)
            start = world.box_positions.copy()
            msg = Evaluate(
                evaluation_id=k + 1,
                genome=genome_to_bytes(genome),
                spec=spec,
                steps=steps,
                step_period=experiment.step_period,
                record=True,
            )
            results = await _evaluate_pair(runners, msg)
            boxes = {"start": start, "end": world.box_positions} if len(start) else {}
            entries.append(_pair_entry(k, seed, results, experiment.evaluation_steps, boxes))
    data = {
        "scenario": experiment.scenario,
        "robots": experiment.robots,
        "steps": steps,
        "evaluation_steps": experiment.evaluation_steps,
        "experiment": msgspec.to_builtins(experiment),
        "median_fitness": float(np.median([e["fitness"] for e in entries])),
        "pairs": entries,
    }
    write_atomic(out / BASELINE_FILE, json.dumps(data, indent=1).encode("utf-8"))
    return data


def load_baseline(path: str | Path) -> dict[str, Any]:
    """``baseline.json`` from a baseline directory (or the file itself)."""
    path = Path(path)
    if path.is_dir():
        path = path / BASELINE_FILE
    return json.loads(path.read_text(encoding="utf-8"))
