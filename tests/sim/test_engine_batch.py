"""Many swarms in one compiled call: each gets, to the last bit, what it gets alone."""

from __future__ import annotations

import numpy as np
import pytest

from master_service.experiments.simulation_setup import (
    simulated_safety,
    simulation_experiment,
    world_config,
)
from minimize_surprise.network import GenomeLayout, spec_from_config
from simulator.engine import Swarm, evaluate_swarms


def _swarms(scenario: str, seeds: list[int]) -> tuple[list[Swarm], list[np.ndarray]]:
    swarms, genomes = [], []
    for seed in seeds:
        experiment = simulation_experiment(scenario, setting="paper", seed=seed)
        spec = spec_from_config(experiment)
        swarms.append(Swarm(world_config(experiment), simulated_safety(experiment), spec, seed))
        genomes.append(np.random.default_rng(seed).uniform(-1, 1, GenomeLayout(spec).size))
    return swarms, genomes


def _same(a, b) -> None:
    assert np.array_equal(a.fitness, b.fitness)
    assert a.interventions == b.interventions
    for name in ("sensors", "predictions", "actions", "commands", "reasons", "poses", "boxes"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None and y is None) or np.array_equal(x, y), name


@pytest.mark.parametrize("scenario", ["basic", "boxes"])
def test_a_batch_gives_each_swarm_what_it_gets_alone(scenario):
    # Three runs of different seeds (different arenas, boxes and genomes) stepped together, two
    # evaluations and a recorded one, against each run alone: every fitness, safety count,
    # trace, pose and box identical.
    seeds = [1, 2, 3]
    together, genomes = _swarms(scenario, seeds)
    alone, _ = _swarms(scenario, seeds)
    for steps, record in [(60, False), (45, False), (30, True)]:
        batch = evaluate_swarms(together, genomes, steps, record=record)
        for swarm, genome, result in zip(alone, genomes, batch, strict=True):
            _same(result, swarm.evaluate(genome, steps, record=record))
        genomes = [g * 0.9 + 0.05 for g in genomes]  # the next candidates
    for a, b in zip(together, alone, strict=True):
        assert a.world.steps == b.world.steps == 60 + 1 + 45 + 1 + 30 + 1
        assert np.array_equal(a.world.kernel_state[0], b.world.kernel_state[0])
        assert np.array_equal(a.world.kernel_state[3], b.world.kernel_state[3])
        assert np.array_equal(a.safety, b.safety)
        assert a.snapshot() == b.snapshot()


def test_swarms_of_different_shapes_are_not_batched():
    (basic,), (g,) = _swarms("basic", [1])
    (boxes,), (h,) = _swarms("boxes", [1])
    with pytest.raises(ValueError, match="same network shape, robots, sensors"):
        evaluate_swarms([basic, boxes], [g, h], 5)
    with pytest.raises(ValueError, match="one each"):
        evaluate_swarms([basic], [g, g], 5)


@pytest.mark.parametrize("scenario", ["basic", "boxes"])
def test_recording_only_poses_changes_nothing_but_what_is_kept(scenario):
    # A behaviour's measures need the poses and boxes alone (MAP-Elites): recording only them
    # gives the fitness, safety counts, poses, boxes and world the whole recording gives.
    seeds = [4, 5]
    whole, genomes = _swarms(scenario, seeds)
    poses, _ = _swarms(scenario, seeds)
    full = evaluate_swarms(whole, genomes, 40, record=True)
    only = evaluate_swarms(poses, genomes, 40, record="poses")
    for a, b in zip(full, only, strict=True):
        assert np.array_equal(a.fitness, b.fitness) and a.interventions == b.interventions
        assert np.array_equal(a.poses, b.poses) and np.array_equal(a.boxes, b.boxes)
        assert b.sensors is None and b.predictions is None and b.reasons is None
    for a, b in zip(whole, poses, strict=True):
        assert a.snapshot() == b.snapshot()
