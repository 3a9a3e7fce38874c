"""The full ``basic`` experiment in lockstep: 1000 evaluations of 100 steps with 10 robots, plus
the post-evaluation, through the real master and agents over loopback TCP (``surprise-master sim``).

Prints ``name: value unit`` lines. Target: <= 60 s on one core (``--cpu 0`` pins the process).
Run: ``python benchmarks/experiment.py [--evaluations N] [--scenario S] [--seed S] [--cpu C]``
"""

from __future__ import annotations

import argparse
import asyncio
import os
import tempfile
import time

from master_service.experiments.simulate import SimulatedSwarm, quiet_agents, simulation_experiment


def main() -> None:
    """Run the experiment once and print its figures."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenario", default="basic")
    parser.add_argument("--evaluations", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cpu", type=int, help="pin the process to this core")
    args = parser.parse_args()
    if args.cpu is not None:
        os.sched_setaffinity(0, {args.cpu})
    experiment = simulation_experiment(args.scenario, evaluations=args.evaluations, seed=args.seed)
    with tempfile.TemporaryDirectory() as tmp, quiet_agents():
        started = time.perf_counter()
        cpu_started = time.process_time()
        result = asyncio.run(SimulatedSwarm(experiment).run(f"{tmp}/run"))
        wall = time.perf_counter() - started
        cpu = time.process_time() - cpu_started
    steps = experiment.evaluation_steps * experiment.evolution.evaluations
    steps += experiment.post_evaluation_steps
    simulated = steps * experiment.step_period
    name = f"experiment_{args.scenario}"
    print(f"{name}_wall_time: {wall:.1f} s")
    print(f"{name}_cpu_time: {cpu:.1f} s")
    print(f"{name}_faster_than_real_time: {simulated / wall:.0f} x")
    robot_steps = steps * experiment.robots
    print(f"{name}_robot_steps_per_s: {robot_steps / wall:.0f} robot-steps/s")
    print(f"{name}_best_fitness: {result.summary.best_fitness:.4f}")
    behaviour = (result.metrics.get("post_evaluation") or {}).get("behaviour") or {}
    if behaviour:
        print(f"{name}_behaviour: {behaviour['motion']}, {behaviour['grouping']}")


if __name__ == "__main__":
    main()
