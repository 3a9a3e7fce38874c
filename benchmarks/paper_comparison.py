"""The paper's comparison (its Sec. V-B and V-C) on our simulator: the median best fitness of
evolved runs against the fitness of random network pairs, per scenario, and the behaviours found.

Each evolved run is a full ``surprise-master sim`` experiment on the engine in the chosen setting
(default ``paper``: the authors' Webots simulation; 1000 evaluations of 1000 steps of 10 ms) with
seeds 1..runs; the random pairs are one ``surprise-master baseline`` of ``pairs`` pairs. Prints
``name: value unit`` lines, and keeps the runs in ``--out`` when given. Run:
``python benchmarks/paper_comparison.py [--scenario basic boxes gradient] [--runs 5] [--pairs 20]
[--setting paper] [--arena 1.0] [--out DIR]``

The paper reports, for Webots: evolved at least 0.88 (basic) and 0.97 (object manipulation),
random pairs at most 0.58, and pushing behaviours (d_B > 0.1 m) among the object-manipulation
runs.
"""

from __future__ import annotations

import argparse
import collections
import statistics
import tempfile
import time
from pathlib import Path

from master_service.experiments.baseline import run_baseline
from master_service.experiments.engine_run import FastRun
from master_service.experiments.simulation_setup import simulation_experiment
from simulator import metrics as sim_metrics


def compare(
    scenario: str, runs: int, pairs: int, setting: str, arena: float | None, out: Path
) -> None:
    """Run and print one scenario's comparison into ``out``."""
    best, classes, pushing = [], collections.Counter(), []
    for seed in range(1, runs + 1):
        started = time.perf_counter()
        experiment = simulation_experiment(scenario, setting=setting, arena=arena, seed=seed)
        result = FastRun(experiment).run(out / f"{scenario}-run-{seed}")
        best.append(result.summary.best_fitness)
        b = result.metrics["post_evaluation"]["behaviour"]
        kind = sim_metrics.behaviour_label(b, "/")
        if b.get("pushing") is not None:
            pushing.append(b["box_displacement"])
        classes[kind] += 1
        print(
            f"{scenario}_run_{seed}_best_fitness: {best[-1]:.4f} "
            f"({kind}, post-evaluation {result.summary.post_evaluation_fitness:.4f}, "
            f"{time.perf_counter() - started:.0f} s)",
            flush=True,
        )
    random_experiment = simulation_experiment(scenario, setting=setting, arena=arena, seed=100)
    baseline = run_baseline(random_experiment, pairs, out / f"{scenario}-random")
    fitness = [p["fitness"] for p in baseline["pairs"]]
    print(f"{scenario}_evolved_median_best_fitness: {statistics.median(best):.4f}")
    print(f"{scenario}_evolved_min_best_fitness: {min(best):.4f}")
    print(f"{scenario}_random_median_fitness: {statistics.median(fitness):.4f}")
    print(f"{scenario}_random_max_fitness: {max(fitness):.4f}")
    print(f"{scenario}_evolved_behaviours: {dict(classes)}")
    if pushing:
        print(f"{scenario}_box_displacement_max: {max(pushing):.3f} m", flush=True)


def main() -> None:
    """Parse the options and run every scenario asked for."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenario", nargs="+", default=["basic", "boxes", "gradient"])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--pairs", type=int, default=20)
    parser.add_argument("--setting", default="paper")
    parser.add_argument("--arena", type=float, help="carpet side in metres (basic)")
    parser.add_argument("--out", type=Path, help="keep the runs here (default: a temporary dir)")
    args = parser.parse_args()
    if args.out is not None:
        for scenario in args.scenario:
            compare(scenario, args.runs, args.pairs, args.setting, args.arena, args.out)
        return
    with tempfile.TemporaryDirectory() as tmp:
        for scenario in args.scenario:
            compare(scenario, args.runs, args.pairs, args.setting, args.arena, Path(tmp))


if __name__ == "__main__":
    main()
