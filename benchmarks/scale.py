"""Speed at scale: the cost of one robot-step with 10, 100 and 1000 robots, ours and Enki's.

Every size is the paper's basic scenario (its Webots setting, 10 ms steps) at the basic
arena's density: 10 robots on a 1 m carpet, the carpet's side grown by sqrt(N / 10) (3.16 m for
100 robots, 10 m for 1000), the walls as far beyond it as in the basic arena.

- ``world``: our world alone, stepped inside one compiled loop (every robot's command set, the
  world stepped, every robot's sensors read), random commands up to full speed held for 10
  steps, as ``benchmarks/sim.py`` drives it;
- ``engine``: the whole control step of an evaluation (``simulator.engine.evaluate``: sensors,
  every robot's network pair and surprise score, its safety layer, the world's step) with one
  random genome;
- ``enki``: Enki's bare world (Debian's ``python3-enki2``, run by the system python) stepping as
  many Thymio II on a carpet of the same size at the same step, the robots' commands set and
  their IR and ground values read every step (``benchmarks/sim.py``'s Enki probe).

Times are CPU time of this process (Enki: of its subprocess) pinned to one core; each figure is
the best of ``--repeats`` runs (as ``timeit`` does), the median printed beside the world's. Each
run steps about ``--robot-steps`` robot-steps (at least ``--min-steps`` steps; Enki, whose
cost grows faster, a tenth of them). Prints ``name: value unit`` lines: the cost per robot-step
in ns at each size, Enki's over ours at each size, and ours at 1000 robots over ours at 10.

Targets (issue 25): ours at 1000 robots at most 1.5 times ours at 10 (contacts and IR sensing
find their neighbours in a cell grid above ``simulator.physics.GRID_ROBOTS`` robots instead of
looking at every pair), and ahead of Enki at every size.

Run: ``python benchmarks/scale.py [--sizes 10 100 1000] [--robot-steps 1000000] [--repeats 3]
[--no-engine]``
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numba  # noqa: E402
import numpy as np  # noqa: E402

from master_service.experiments.simulation_setup import (  # noqa: E402
    simulated_safety,
    simulation_experiment,
    world_config,
)
from minimize_surprise.config import ExperimentConfig  # noqa: E402
from minimize_surprise.network import GenomeLayout, spec_from_config  # noqa: E402
from simulator import physics  # noqa: E402
from simulator.engine import Swarm  # noqa: E402
from simulator.physics import Geometry, Sensing  # noqa: E402
from simulator.world import World  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sim import enki_python, enki_runs, pin_to_one_core  # noqa: E402

#: The basic scenario's robots and carpet side (m): the density every size keeps.
BASIC_ROBOTS = 10
BASIC_SIDE = 1.0
#: Steps a random command is held.
HOLD = 10


def carpet_side(robots: int) -> float:
    """The carpet's side (m) that holds ``robots`` at the basic scenario's density."""
    return BASIC_SIDE * math.sqrt(robots / BASIC_ROBOTS)


def experiment_at(robots: int, seed: int = 1) -> ExperimentConfig:
    """The paper setting's basic experiment with ``robots`` robots at the basic density."""
    return simulation_experiment(
        "basic", setting="paper", arena=carpet_side(robots), robots=robots, seed=seed
    )


# Not cached on disk: numba's cache of a function does not notice changes to the kernels it
# calls, and a benchmark must measure the kernels as they are.
@numba.njit
def _world_steps(
    g: Geometry, sn: Sensing, pose: np.ndarray, cmd: np.ndarray, force: np.ndarray,
    boxes: np.ndarray, pending: np.ndarray, commands: np.ndarray, values: np.ndarray,
    work: physics.SenseWork, steps: int,
) -> None:  # fmt: skip
    # ``steps`` steps: commands (steps // HOLD + 1, N, 2), each held for HOLD steps.
    for t in range(steps):
        physics.clamp_commands(commands[t // HOLD], cmd)
        physics.step_world(g, pose, cmd, force, boxes, pending, 0, len(boxes), sn.need_force, True)
        physics.sense(sn, pose, force, t + 1, values, work, True)


def time_world(robots: int, steps: int, seed: int = 1) -> float:
    """CPU seconds per step of our world with ``robots`` robots (see the module docstring)."""
    world = World(world_config(experiment_at(robots, seed)), seed=seed)
    rng = np.random.default_rng(seed)
    commands = rng.uniform(-1.0, 1.0, size=(steps // HOLD + 1, robots, 2))
    g, sn = world.kernel_constants
    pose, cmd, force, boxes, pending = world.kernel_state
    values = np.empty((robots, len(world.sensors)))
    work = physics.sense_work(robots)
    _world_steps(g, sn, pose, cmd, force, boxes, pending, commands, values, work, 20)  # warm-up
    world.reset()
    pose, cmd, force, boxes, pending = world.kernel_state
    cpu = time.process_time()
    _world_steps(g, sn, pose, cmd, force, boxes, pending, commands, values, work, steps)
    return (time.process_time() - cpu) / steps


def time_engine(robots: int, steps: int, seed: int = 1) -> float:
    """CPU seconds per step of a whole evaluation's control step with ``robots`` robots."""
    experiment = experiment_at(robots, seed)
    spec = spec_from_config(experiment)
    swarm = Swarm(world_config(experiment), simulated_safety(experiment), spec, seed)
    genome = np.random.default_rng(seed).uniform(-1.0, 1.0, GenomeLayout(spec).size)
    swarm.evaluate(genome, 20)  # compiled before the clock starts
    cpu = time.process_time()
    swarm.evaluate(genome, steps)
    return (time.process_time() - cpu) / (steps + 1)  # the final stop is a step too


def time_enki(python: str, robots: int, steps: int, repeats: int, seed: int = 1) -> list[float]:
    """CPU seconds per step of Enki's bare world with ``robots`` robots, one per repeat."""
    config = world_config(experiment_at(robots, seed))
    runs = enki_runs(python, config, steps, seed, repeats, config.dt)
    return [run["cpu_per_step"] for run in runs]


def ns(per_step: float, robots: int) -> float:
    """Nanoseconds per robot-step of ``per_step`` seconds per step of ``robots`` robots."""
    return per_step / robots * 1e9


def main() -> None:
    """Measure every size and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10, 100, 1000])
    parser.add_argument("--robot-steps", type=int, default=1_000_000)
    parser.add_argument("--min-steps", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-engine", action="store_true", help="skip the whole control step")
    parser.add_argument("--enki-python", default="/usr/bin/python3")
    args = parser.parse_args()
    pin_to_one_core()
    python = enki_python(args.enki_python)
    if python is None:
        print(f"Enki skipped: {args.enki_python} cannot import pyenki", file=sys.stderr)
    world: dict[int, float] = {}
    engine: dict[int, float] = {}
    for n in args.sizes:
        steps = max(args.min_steps, args.robot_steps // n)
        runs = [ns(time_world(n, steps), n) for _ in range(args.repeats)]
        world[n] = min(runs)
        print(f"scale_world_ns_per_robot_step_{n}: {world[n]:.0f} ns")
        print(f"scale_world_ns_per_robot_step_{n}_median: {statistics.median(runs):.0f} ns")
        if not args.no_engine:
            engine[n] = min(ns(time_engine(n, steps), n) for _ in range(args.repeats))
            print(f"scale_engine_ns_per_robot_step_{n}: {engine[n]:.0f} ns")
        if python is not None:
            enki_steps = max(args.min_steps // 10, args.robot_steps // 10 // n)
            enki = ns(min(time_enki(python, n, enki_steps, args.repeats)), n)
            print(f"scale_enki_ns_per_robot_step_{n}: {enki:.0f} ns")
            print(f"scale_enki_vs_world_{n}: {enki / world[n]:.2f} x")
            if n in engine:
                print(f"scale_enki_vs_engine_{n}: {enki / engine[n]:.2f} x")
    small, large = min(args.sizes), max(args.sizes)
    if small != large:
        print(f"scale_world_{large}_vs_{small}: {world[large] / world[small]:.2f} x")
        if engine:
            print(f"scale_engine_{large}_vs_{small}: {engine[large] / engine[small]:.2f} x")


if __name__ == "__main__":
    main()
