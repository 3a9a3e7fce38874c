"""Compile every kernel of the simulator and the method once (numba caches them on disk).

A fresh installation compiles each kernel on its first use, a few seconds each; calling
:func:`warm_up` first moves that cost to a known moment (the start of a test session, of a
benchmark, or of a study's worker) instead of the first step of a timed run.
"""

from __future__ import annotations

import numpy as np

from minimize_surprise.network import GenomeLayout, NetworkPair, NetworkSpec
from minimize_surprise.sensors import ALL_SENSORS
from minimize_surprise.warmup import warm_up_control
from simulator.scenarios import SCENARIOS, scenario_config
from simulator.world import World

__all__ = ["warm_up"]


def warm_up() -> None:
    """Run every kernel once on a tiny input (compiling it if needed)."""
    for name in SCENARIOS:
        world = World(scenario_config(name, {"robots": 2}), seed=0)
        world.set_commands(np.ones((2, 2)))
        world.step()
        world.sensor_matrix()
    for model in ("cone", "ray"):
        world = World(scenario_config("basic", {"robots": 2, "ir_model": model}), seed=0)
        world.step()
        world.sensor_matrix()
    warm_up_control(ALL_SENSORS)
    spec = NetworkSpec(sensors=ALL_SENSORS, actor_hidden=2, predictor_hidden=2)
    genome = np.zeros(GenomeLayout(spec).size)
    NetworkPair(spec, genome, robots=2).step(np.zeros((2, len(ALL_SENSORS))))
