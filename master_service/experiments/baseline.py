"""``surprise-master baseline``: random actor-predictor pairs in the same arena (the paper's
comparison for evolved pairs, Sec. V-B).

Each random pair (a genome drawn as evolution draws its initial genome) runs on every robot of a
freshly reset arena for the post-evaluation length, on the engine (``simulator.engine``: the same
network, safety and scoring kernels the agents run, shown equal to them in the tests). Its
``fitness`` is the swarm fitness over the first ``evaluation_steps`` steps, which is what an
evolved genome's fitness measures; the behaviour metrics cover the whole run, like the
post-evaluation of an evolved genome. ``baseline.json`` holds one entry per pair, the median and
best fitness, and how many pairs showed each behaviour class.
"""

from __future__ import annotations

import collections
import json
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from master_service.experiments.simulation_setup import simulated_safety, world_config
from minimize_surprise.config import ExperimentConfig
from minimize_surprise.evolution import random_genome
from minimize_surprise.fitness import surprise_fitness, swarm_fitness
from minimize_surprise.network import GenomeLayout, spec_from_config
from runfiles.schema import BASELINE_FILE, load_baseline, write_atomic
from simulator import metrics as sim_metrics
from simulator.engine import EvaluationRecord, Swarm

__all__ = ["BASELINE_FILE", "load_baseline", "run_baseline"]


def _pair_entry(
    index: int,
    seed: int,
    record: EvaluationRecord,
    evaluation_steps: int,
    boxes: dict[str, Any],
    dt: float,
) -> dict[str, Any]:
    assert record.sensors is not None and record.predictions is not None
    assert record.poses is not None
    steps = min(evaluation_steps, record.sensors.shape[0])
    fitnesses = [
        surprise_fitness(record.predictions[:steps, i], record.sensors[:steps, i])
        for i in range(record.sensors.shape[1])
    ]
    behaviour = sim_metrics.behaviour_metrics(
        record.poses, boxes.get("start"), boxes.get("end"), dt=dt
    )
    # Mean over robots and the scored steps of each sensor and of its prediction (made a step
    # before), as the report shows them for an evolved genome.
    mean_sensors = record.sensors[1:steps].mean(axis=(0, 1))
    mean_predictions = record.predictions[: steps - 1].mean(axis=(0, 1))
    return {
        "pair": index,
        "arena_seed": seed,
        "fitness": swarm_fitness(fitnesses),
        "post_fitness": swarm_fitness([float(f) for f in record.fitness]),
        "robot_fitness": fitnesses,
        "behaviour": msgspec.to_builtins(behaviour),
        "mean_sensors": mean_sensors.tolist(),
        "mean_predictions": mean_predictions.tolist(),
    }


def run_baseline(experiment: ExperimentConfig, pairs: int, out: str | Path) -> dict[str, Any]:
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
    swarm = Swarm(world_config(experiment), simulated_safety(experiment), spec, experiment.seed)
    world = swarm.world
    entries = []
    for k in range(pairs):
        genome = random_genome(rng, size, experiment.evolution.initial_range)
        seed = experiment.seed + 1 + k
        world.reset(seed=seed)
        start = world.box_positions.copy()
        record = swarm.evaluate(genome, steps, record=True)
        boxes = {"start": start, "end": world.box_positions.copy()} if len(start) else {}
        entries.append(
            _pair_entry(k, seed, record, experiment.evaluation_steps, boxes, experiment.step_period)
        )
    data = {
        "scenario": experiment.scenario,
        "setting": experiment.setting,
        "robots": experiment.robots,
        "steps": steps,
        "evaluation_steps": experiment.evaluation_steps,
        "experiment": msgspec.to_builtins(experiment),
        "median_fitness": float(np.median([e["fitness"] for e in entries])),
        "best_fitness": float(np.max([e["fitness"] for e in entries])),
        # How many pairs showed each behaviour class (docs/method.md), per kind of class.
        "behaviour_counts": {
            key: dict(collections.Counter(e["behaviour"][key] for e in entries).most_common())
            for key in ("motion", "grouping", "manipulation")
            if any(e["behaviour"].get(key) is not None for e in entries)
        },
        "pairs": entries,
    }
    write_atomic(out / BASELINE_FILE, json.dumps(data, indent=1).encode("utf-8"))
    return data
