"""The agent's real-time control loop: period accuracy and work per step.

Runs one evaluation through :class:`robot_agent.runner.EvaluationRunner` (network, safety layer,
watchdog) on a :class:`~drivers.clock.MonotonicClock` against a simulated robot (``simulator`` in
real-time mode, one robot in the basic arena; a constant fake body if ``simulator`` is missing),
for ``--seconds`` of wall time. Prints one figure a line as ``name: value unit``:

- ``period_error``: |interval between consecutive step starts - period|;
- ``wake_lateness``: how late the loop woke up after each deadline it slept to;
- ``work``: from the start of a step (the sensor read) to the moment it sleeps.

Targets: mean period error <= 0.1 ms, p99 <= 2 ms; work per step <= 5 ms at p99.
Run: ``python benchmarks/agent_loop.py --seconds 10 [--body fake]``
"""

from __future__ import annotations

import argparse
import asyncio
import os
import time

import numpy as np

from drivers.body import Body, SensorFrame
from drivers.clock import Clock, MonotonicClock
from minimize_surprise.network import GenomeLayout, NetworkSpec
from minimize_surprise.sensors import GROUND_SENSORS, IR_SENSORS
from minimize_surprise.wire import Evaluate, Result, genome_to_bytes
from robot_agent.config import LoopConfig
from robot_agent.runner import EvaluationRunner
from robot_agent.watchdog import Watchdog

PERIOD = 0.1
SENSORS = IR_SENSORS + GROUND_SENSORS


class TimedClock(Clock):
    """A clock that records when the loop goes to sleep, its deadline and when it wakes."""

    def __init__(self, inner: Clock) -> None:
        self.inner = inner
        self.sleeps: list[tuple[float, float, float]] = []  # (called, deadline, woke)

    def now(self) -> float:
        return self.inner.now()

    async def sleep_until(self, deadline: float) -> None:
        called = time.monotonic()
        await self.inner.sleep_until(deadline)
        self.sleeps.append((called, deadline, time.monotonic()))


class TimedBody(Body):
    """Wraps a body and records when each step starts (its sensor read)."""

    def __init__(self, inner: Body) -> None:
        self.inner = inner
        self.starts: list[float] = []

    @property
    def sensors(self) -> tuple[str, ...]:
        return self.inner.sensors

    async def read(self) -> SensorFrame:
        self.starts.append(time.monotonic())
        return await self.inner.read()

    async def drive(self, left: float, right: float) -> None:
        await self.inner.drive(left, right)

    async def stop(self) -> None:
        await self.inner.stop()


class ConstantBody(Body):
    """Fallback when simulator is not available: constant readings, motors ignored."""

    @property
    def sensors(self) -> tuple[str, ...]:
        return SENSORS

    async def read(self) -> SensorFrame:
        return SensorFrame(values=np.full(len(SENSORS), 0.1), timestamp=time.monotonic())

    async def drive(self, left: float, right: float) -> None:
        pass

    async def stop(self) -> None:
        pass


def _load() -> str:
    # Timing figures mean little on a busy machine; say how busy it was.
    try:
        one, five, _ = os.getloadavg()
    except OSError:
        return "unknown"
    return f"{one:.1f} (1 min), {five:.1f} (5 min) on {os.cpu_count()} CPUs"


def percentile_ms(values: np.ndarray, q: float) -> float:
    """The ``q``-th percentile of ``values`` (seconds) in milliseconds."""
    return float(np.percentile(values, q) * 1e3) if values.size else float("nan")


async def measure(seconds: float, body_kind: str) -> None:
    """Run the evaluation and print the figures."""
    steps = max(2, round(seconds / PERIOD))
    swarm = None
    inner: Body = ConstantBody()
    source = "constant fake body"
    if body_kind == "sim":
        try:
            from simulator.body import SimSwarm
            from simulator.scenarios import scenario_config
            from simulator.world import World
        except ImportError:
            print("# simulator is not available; using the constant fake body")
        else:
            swarm = SimSwarm(World(scenario_config("basic", {"robots": 1}), 0), realtime=True)
            inner = swarm.body(0, SENSORS)
            source = "simulator (real time)"
    body = TimedBody(inner)
    clock = TimedClock(MonotonicClock())
    watchdog = Watchdog(body.stop)
    runner = EvaluationRunner(body, clock, loop=LoopConfig(), watchdog=watchdog)
    spec = NetworkSpec(sensors=SENSORS, actor_hidden=8, predictor_hidden=len(SENSORS) + 1)
    genome = np.random.default_rng(0).uniform(-0.5, 0.5, GenomeLayout(spec).size)
    msg = Evaluate(
        evaluation_id=0,
        genome=genome_to_bytes(genome),
        spec=spec,
        steps=steps,
        step_period=PERIOD,
    )

    print(f"# body: {source}; {steps} steps at {PERIOD * 1e3:.0f} ms; load {_load()}")
    async with watchdog:
        if swarm is not None:
            await swarm.start()
        try:
            outcome = await runner.run(msg)
        finally:
            if swarm is not None:
                await swarm.stop()
    if not isinstance(outcome, Result):
        raise SystemExit(f"the evaluation failed: {outcome.reason}")

    starts = np.array(body.starts)
    sleeps = np.array(clock.sleeps)
    period_error = np.abs(np.diff(starts) - PERIOD)
    lateness = sleeps[:, 2] - sleeps[:, 1]
    # A step's work ends when it goes to sleep (steps that overran never slept: not counted);
    # its start is the last read before that moment.
    step_of_sleep = np.searchsorted(starts, sleeps[:, 0], side="right") - 1
    work = sleeps[:, 0] - starts[step_of_sleep]
    print(f"steps: {outcome.stats.steps_run} steps")
    print(f"overruns: {outcome.stats.overruns} steps")
    print(f"period_error_mean: {period_error.mean() * 1e3:.4f} ms")
    print(f"period_error_p99: {percentile_ms(period_error, 99):.4f} ms")
    print(f"period_error_max: {period_error.max() * 1e3:.4f} ms")
    print(f"wake_lateness_mean: {lateness.mean() * 1e3:.4f} ms")
    print(f"wake_lateness_p99: {percentile_ms(lateness, 99):.4f} ms")
    print(f"work_mean: {work.mean() * 1e3:.4f} ms")
    print(f"work_p99: {percentile_ms(work, 99):.4f} ms")
    print(f"work_max: {work.max() * 1e3:.4f} ms")
    print(f"fitness: {outcome.fitness:.4f} 1")


def main() -> None:
    """Parse the arguments and run."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="duration (default 60)")
    parser.add_argument(
        "--body",
        choices=["sim", "fake"],
        default="sim",
        help="simulator's simulated robot (default) or a constant fake body",
    )
    args = parser.parse_args()
    asyncio.run(measure(args.seconds, args.body))


if __name__ == "__main__":
    main()
