"""Speed of the simulated world: steps per second with random commands.

Each step includes computing every robot's sensor values, as the agents read them every step.
Commands are random and held for 1 s (10 steps) so that robots travel, meet and push boxes.
Times are CPU time of this process pinned to one core (``time.process_time``), so that a busy
machine distorts them less; each figure is the best of ``--repeats`` runs (as ``timeit`` does),
with the median of the runs printed too, and wall-clock time for comparison.

Targets (issue 3): at least 50,000 robot-steps/s for ``basic`` (10 robots) and at most 1 ms per
step for ``gradient`` (4 robots, all 271 boxes).

Run: ``python benchmarks/sim.py [--steps N] [--seed S]``. Every figure is printed on its own line
as ``name: value unit``.
"""

from __future__ import annotations

import os

# One core: keep numpy's thread pools (unused by these small arrays anyway) to one thread.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from sim_stub.scenarios import scenario_config  # noqa: E402
from sim_stub.world import World  # noqa: E402


def pin_to_one_core() -> None:
    """Run on a single CPU where the platform allows it."""
    if hasattr(os, "sched_setaffinity"):
        cpus = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpus[-1]})


def measure(scenario: str, steps: int, seed: int) -> dict[str, float]:
    """Step a fresh world of ``scenario``; return CPU and wall seconds per step and more."""
    world = World(scenario_config(scenario), seed=seed)
    n = world.n_robots
    rng = np.random.default_rng(seed)
    commands = rng.uniform(-1.0, 1.0, size=(steps // 10 + 1, n, 2))
    for _ in range(50):  # warm-up: first-call costs of numpy and the caches
        world.set_commands(commands[0])
        world.step()
        world.sensor_matrix()
    world.reset()
    force_steps = 0
    cpu0, wall0 = time.process_time(), time.perf_counter()
    for k in range(steps):
        world.set_commands(commands[k // 10])
        world.step()
        world.sensor_matrix()
        force_steps += bool(world.forces.any())
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    moved = np.hypot(*(world.box_positions - world.box_start_positions).T) > 1e-9
    return {
        "robots": n,
        "cpu_per_step": cpu / steps,
        "wall_per_step": wall / steps,
        "boxes_moved": int(moved.sum()),
        "pushing_steps": force_steps / steps,
    }


def best_of(scenario: str, steps: int, seed: int, repeats: int) -> dict[str, float]:
    """``measure`` ``repeats`` times; the fastest run, with the median CPU time added."""
    runs = [measure(scenario, steps, seed) for _ in range(repeats)]
    best = min(runs, key=lambda r: r["cpu_per_step"])
    best["median_cpu_per_step"] = float(np.median([r["cpu_per_step"] for r in runs]))
    return best


def main() -> None:
    """Measure both scenarios and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000, help="steps per run")
    parser.add_argument("--repeats", type=int, default=3, help="runs per scenario")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    pin_to_one_core()

    basic = best_of("basic", args.steps, args.seed, args.repeats)
    n = basic["robots"]
    print(f"basic_robot_steps_per_s: {n / basic['cpu_per_step']:.0f} robot-steps/s")
    print(f"basic_robot_steps_per_s_median: {n / basic['median_cpu_per_step']:.0f} robot-steps/s")
    print(f"basic_robot_steps_per_s_wall: {n / basic['wall_per_step']:.0f} robot-steps/s")
    print(f"basic_step_time: {basic['cpu_per_step'] * 1e6:.1f} us")

    gradient = best_of("gradient", args.steps, args.seed, args.repeats)
    print(f"gradient_step_time: {gradient['cpu_per_step'] * 1e3:.3f} ms")
    print(f"gradient_step_time_median: {gradient['median_cpu_per_step'] * 1e3:.3f} ms")
    print(f"gradient_step_time_wall: {gradient['wall_per_step'] * 1e3:.3f} ms")
    n = gradient["robots"]
    print(f"gradient_robot_steps_per_s: {n / gradient['cpu_per_step']:.0f} robot-steps/s")
    print(f"gradient_boxes_moved: {gradient['boxes_moved']} boxes")
    print(f"gradient_pushing_steps: {gradient['pushing_steps'] * 100:.1f} %")


if __name__ == "__main__":
    main()
