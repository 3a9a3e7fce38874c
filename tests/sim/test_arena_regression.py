"""The shipped arenas give, for the same seeds, the same results to the bit as the scenarios did
before arenas became files (figures recorded at commit bbe9183, before the change).

Each case runs one scenario in one setting on both engines' cores: the compiled engine
(``Swarm.evaluate``: two evaluations and a recorded one) and the stepped world the agents engine
drives (``World.step`` under seeded commands). The digest covers every fitness, pose, box and
sensor value. Regenerate only for a deliberate change of the simulation:
``python -m tests.sim.test_arena_regression --write``.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from master_service.experiments.simulation_setup import (
    simulated_safety,
    simulation_experiment,
    world_config,
)
from minimize_surprise.network import GenomeLayout, spec_from_config
from simulator.engine import Swarm
from simulator.world import World

GOLDEN = Path(__file__).with_name("golden") / "arenas_before.json"
CASES = [
    (scenario, setting)
    for scenario in ("basic", "boxes", "gradient")
    for setting in ("paper", "lab")
]
STEPS = 120  # enough for contacts, boxes pushed and the safety layer to act


def _digest(arrays: list[np.ndarray]) -> str:
    hasher = hashlib.sha256()
    for array in arrays:
        data = np.ascontiguousarray(array)
        hasher.update(str(data.dtype).encode() + str(data.shape).encode())
        hasher.update(data.tobytes())
    return hasher.hexdigest()


def _figures(scenario: str, setting: str, seed: int = 7) -> dict[str, object]:
    experiment = simulation_experiment(scenario, setting=setting, seed=seed)
    config = world_config(experiment)
    spec = spec_from_config(experiment)
    swarm = Swarm(config, simulated_safety(experiment), spec, seed)
    genome = np.random.default_rng(seed).uniform(-1, 1, GenomeLayout(spec).size)
    engine: list[np.ndarray] = []
    fitness: list[float] = []
    for record in (False, False, True):
        result = swarm.evaluate(genome, STEPS, record=record)
        fitness.append(float(np.mean(result.fitness)))
        engine.append(np.asarray(result.fitness))
        for name in ("poses", "boxes", "sensors", "actions"):
            value = getattr(result, name)
            if value is not None:
                engine.append(np.asarray(value))
        genome = genome * 0.9 + 0.05
    world = World(config, seed=seed, record=True)
    rng = np.random.default_rng(seed)
    stepped: list[np.ndarray] = [world.poses.copy(), world.box_positions.copy()]
    for _ in range(STEPS):
        world.set_commands(rng.uniform(-1, 1, size=(world.n_robots, 2)))
        world.step()
        stepped.append(world.sensor_matrix().copy())
    stepped += [world.recorded_poses(), world.box_positions.copy()]
    return {
        "engine": _digest(engine),
        "world": _digest(stepped),
        "fitness": fitness,
        "boxes": len(world.box_positions),
    }


@pytest.mark.parametrize(("scenario", "setting"), CASES)
def test_the_arena_gives_what_the_scenario_gave(scenario: str, setting: str) -> None:
    recorded = json.loads(GOLDEN.read_text())[f"{scenario}/{setting}"]
    assert _figures(scenario, setting) == recorded


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    GOLDEN.parent.mkdir(exist_ok=True)
    figures = {f"{scenario}/{setting}": _figures(scenario, setting) for scenario, setting in CASES}
    GOLDEN.write_text(json.dumps(figures, indent=1) + "\n")
    print(f"wrote {GOLDEN}")
