"""Forward-pass time of the network pair: one robot, and batched for 10 and 10,000 robots.

Prints one figure a line as ``name: value unit`` (median of repeated timings).
Run: ``python benchmarks/network.py``
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from minimize_surprise.network import GenomeLayout, NetworkPair, NetworkSpec
from minimize_surprise.sensors import GROUND_SENSORS, IR_SENSORS

SPEC = NetworkSpec(sensors=IR_SENSORS + GROUND_SENSORS, actor_hidden=8, predictor_hidden=10)


def median_step_time(robots: int, steps: int, repeats: int = 7) -> float:
    """Median over ``repeats`` of the mean time of one :meth:`NetworkPair.step` call, in seconds."""
    rng = np.random.default_rng(0)
    genome = rng.uniform(-0.5, 0.5, GenomeLayout(SPEC).size)
    net = NetworkPair(SPEC, genome, robots=robots)
    shape = (len(SPEC.sensors),) if robots == 1 else (robots, len(SPEC.sensors))
    inputs = rng.random((steps, *shape))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for s in inputs:
            net.step(s)
        times.append((time.perf_counter() - start) / steps)
    return statistics.median(times)


def main() -> None:
    """Print the figures."""
    one = median_step_time(1, 2000)
    print(f"network_step_1_robot: {one * 1e6:.1f} us")
    ten = median_step_time(10, 2000)
    print(f"network_step_10_robots: {ten * 1e6:.1f} us")
    big = median_step_time(10_000, 50)
    print(f"network_step_10000_robots: {big * 1e3:.2f} ms")
    print(f"network_step_10000_robots_per_robot: {big / 10_000 * 1e9:.0f} ns")


if __name__ == "__main__":
    main()
