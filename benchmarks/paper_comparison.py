"""The paper's comparison (REFERENCE section 8) on our simulator: the median best fitness of
evolved runs against the median fitness of random network pairs, per scenario.

Each evolved run is a full ``surprise-master sim`` experiment (1000 evaluations by default) with
seeds 1..runs; the random pairs are one ``surprise-master baseline`` of ``pairs`` pairs.
Prints ``name: value unit`` lines. Run:
``python benchmarks/paper_comparison.py [--scenario basic boxes gradient] [--runs 5] [--pairs 20]``
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import statistics
import tempfile
import time

from master_service.baseline import run_baseline
from master_service.simulate import SimulatedSwarm, quiet_agents, simulation_experiment


def compare(scenario: str, runs: int, pairs: int, evaluations: int) -> None:
    """Run and print one scenario's comparison."""
    best, classes = [], collections.Counter()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(1, runs + 1):
            started = time.perf_counter()
            experiment = simulation_experiment(scenario, evaluations=evaluations, seed=seed)
            result = asyncio.run(SimulatedSwarm(experiment).run(f"{tmp}/run-{seed}"))
            best.append(result.summary.best_fitness)
            b = result.metrics["post_evaluation"]["behaviour"]
            kind = f"{b['motion']}/{b['grouping']}"
            if b.get("pushing") is not None:
                kind += "/pushing" if b["pushing"] else "/not-pushing"
            classes[kind] += 1
            print(
                f"{scenario}_run_{seed}_best_fitness: {best[-1]:.4f} "
                f"({kind}, {time.perf_counter() - started:.0f} s)",
                flush=True,
            )
        baseline = asyncio.run(
            run_baseline(simulation_experiment(scenario, seed=100), pairs, f"{tmp}/baseline")
        )
    print(f"{scenario}_evolved_median_best_fitness: {statistics.median(best):.4f}")
    print(f"{scenario}_random_median_fitness: {baseline['median_fitness']:.4f}")
    print(f"{scenario}_random_max_fitness: {max(p['fitness'] for p in baseline['pairs']):.4f}")
    print(f"{scenario}_evolved_behaviours: {dict(classes)}", flush=True)


def main() -> None:
    """Parse the options and run every scenario asked for."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenario", nargs="+", default=["basic", "boxes", "gradient"])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--pairs", type=int, default=20)
    parser.add_argument("--evaluations", type=int, default=1000)
    args = parser.parse_args()
    quiet_agents()
    for scenario in args.scenario:
        compare(scenario, args.runs, args.pairs, args.evaluations)


if __name__ == "__main__":
    main()
