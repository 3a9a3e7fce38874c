"""What one control step of the robot's agent costs in computation, as a Pi runs it.

A Pi installed by ``deploy/install-pi.sh`` has the ``robot`` extra only, without numba, so the
step's kernels (networks, score, safety rules; ``minimize_surprise/jit.py``) run as plain Python
over numpy arrays. This benchmark therefore sets ``SURPRISE_NO_JIT=1`` before it imports the
project (``--jit`` keeps numba, where installed, for comparison) and times, per step:

- ``kernels``: the pieces of the step the agent computes, as ``robot_agent/loop.py`` calls them:
  ``SurpriseScore.observe``, ``NetworkPair.step``, ``SurpriseScore.expect``, ``SafetyLayer.step``;
- ``loop``: a whole step of :meth:`robot_agent.loop.ControlLoop.run` (the above, the reading's
  checks, the watchdog's feeds, the timeouts around the body's calls, the deadline bookkeeping,
  three rounds of the event loop) on a body and a clock that cost nothing else: all of a step's
  work on the Pi except the body's own D-Bus and I2C traffic and the sleep itself.

Two configurations: ``basic`` (the paper's basic behaviours, ``deploy/examples/experiment.yaml``:
9 sensors, 8 actor and 10 predictor hidden units, the ``stop`` rules) and ``object`` (object
manipulation: every one of the 12 sensors, 8 and 13 hidden units, the ``escape`` rules). The
readings stay below every threshold, so every rule is checked and none fires (the rules' longest
path without a manoeuvre).

Prints one figure a line as ``name: value unit`` (the median over ``--repeats`` of the mean per
step). ``--only PART --steps N`` runs just N steps of one part and prints nothing else: the
instruction counting under emulation (``benchmarks/pi_step_qemu.sh``) runs it for two step counts
and takes the difference, which leaves out the start-up.

Run: ``python benchmarks/pi_step.py [--jit]``; results and method: docs/robot-agent.md.
"""

from __future__ import annotations

import argparse
import os
import sys

# Before the project's modules are imported: jit.py decides once, at its import.
if "--jit" not in sys.argv[1:]:
    os.environ["SURPRISE_NO_JIT"] = "1"

import asyncio
import statistics
import time
from dataclasses import dataclass

import numpy as np

from drivers.body import Body, SensorFrame
from drivers.clock import Clock
from minimize_surprise import jit
from minimize_surprise.fitness import SurpriseScore
from minimize_surprise.network import GenomeLayout, NetworkPair, NetworkSpec
from minimize_surprise.safety import SafetyConfig, SafetyLayer
from minimize_surprise.sensors import ALL_SENSORS, GROUND_SENSORS, IR_SENSORS
from robot_agent.loop import ControlLoop, sensor_index
from robot_agent.watchdog import Watchdog

PERIOD = 0.1
#: Distinct readings cycled through (drawn once, below every threshold of the rules).
FRAMES = 64


@dataclass(frozen=True)
class Setup:
    """One robot's experiment: its body's sensors, the network's and the rules' profile."""

    body_sensors: tuple[str, ...]
    sensors: tuple[str, ...]
    actor_hidden: int
    predictor_hidden: int
    profile: str


SETUPS = {
    "basic": Setup(IR_SENSORS + GROUND_SENSORS, IR_SENSORS + GROUND_SENSORS, 8, 10, "stop"),
    "object": Setup(ALL_SENSORS, ALL_SENSORS, 8, 13, "escape"),
}


def readings(count: int) -> np.ndarray:
    """``FRAMES`` readings of ``count`` sensors, all below the rules' thresholds (<= 0.3)."""
    return np.random.default_rng(1).uniform(0.0, 0.3, (FRAMES, count))


def network(setup: Setup) -> NetworkPair:
    """A network pair of the setup's shape with a random genome (the paper's initial range)."""
    spec = NetworkSpec(
        sensors=setup.sensors,
        actor_hidden=setup.actor_hidden,
        predictor_hidden=setup.predictor_hidden,
    )
    genome = np.random.default_rng(0).uniform(-0.5, 0.5, GenomeLayout(spec).size)
    return NetworkPair(spec, genome)


def run_kernels(setup: Setup, steps: int) -> float:
    """``steps`` steps of the kernels as the loop calls them; seconds per step."""
    net = network(setup)
    layer = SafetyLayer(setup.body_sensors, SafetyConfig(profile=setup.profile))  # type: ignore[arg-type]
    state = layer.initial_state(7)
    frames = readings(len(setup.body_sensors))
    index = sensor_index(setup.sensors, setup.body_sensors)
    score = SurpriseScore()
    began = time.perf_counter()
    for k in range(steps):
        values = frames[k % FRAMES]
        s = values if index is None else values[index]
        score.observe(s)
        action, prediction = net.step(s)
        score.expect(prediction)
        state = layer.step(state, values, action, age=0.0).state
    return (time.perf_counter() - began) / steps


class StepClock(Clock):
    """A clock that stands still during a step and jumps to the deadline it is asked to sleep
    to: no step overruns, however slowly it runs (under emulation too)."""

    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t

    async def sleep_until(self, deadline: float) -> None:
        self.t = max(self.t, deadline)
        await asyncio.sleep(0)  # one round of the event loop, as a real sleep's wake-up


class FreeBody(Body):
    """A body whose reads and drives cost nothing but one round of the event loop each (a real
    body awaits its reply); ``blocking`` as the Thymio's (a timeout around every call, as on the
    robot)."""

    blocking = True

    def __init__(self, sensors: tuple[str, ...], clock: StepClock) -> None:
        self._sensors = sensors
        self._clock = clock
        self._frames = readings(len(sensors))
        self._k = 0

    @property
    def sensors(self) -> tuple[str, ...]:
        return self._sensors

    async def read(self) -> SensorFrame:
        self._k += 1
        await asyncio.sleep(0)  # one round of the event loop, as waiting for medulla's reply
        return SensorFrame(values=self._frames[self._k % FRAMES], timestamp=self._clock.now())

    async def drive(self, left: float, right: float) -> None:
        await asyncio.sleep(0)

    async def stop(self) -> None:
        pass


async def _run_loop(setup: Setup, steps: int) -> float:
    clock = StepClock()
    body = FreeBody(setup.body_sensors, clock)
    layer = SafetyLayer(setup.body_sensors, SafetyConfig(profile=setup.profile))  # type: ignore[arg-type]
    # Fed every step but not started: its checks run on wall time, not per step.
    watchdog = Watchdog(body.stop)
    loop = ControlLoop(body, clock, layer, watchdog=watchdog)
    net = network(setup)
    index = sensor_index(setup.sensors, setup.body_sensors)
    began = time.perf_counter()
    outcome = await loop.run(net, index, steps, layer.initial_state(7), period=PERIOD)
    seconds = (time.perf_counter() - began) / steps
    if outcome.failure is not None or outcome.stats.overruns:
        raise SystemExit(f"the loop did not run cleanly: {outcome.failure} {outcome.stats}")
    return seconds


def run_loop(setup: Setup, steps: int) -> float:
    """``steps`` steps of the control loop on a free body; seconds per step."""
    return asyncio.run(_run_loop(setup, steps))


PARTS = {"kernels": run_kernels, "loop": run_loop}


def median_per_step(part: str, setup: Setup, steps: int, repeats: int) -> float:
    """The median over ``repeats`` runs (after one run to warm up) of seconds per step."""
    run = PARTS[part]
    run(setup, min(steps, 50))
    return statistics.median(run(setup, steps) for _ in range(repeats))


def main() -> None:
    """Parse the arguments; print the figures, or run one part for ``--only``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jit", action="store_true", help="keep numba (if installed)")
    parser.add_argument("--steps", type=int, default=500, help="steps per timed run")
    parser.add_argument("--repeats", type=int, default=7, help="timed runs per figure")
    parser.add_argument(
        "--only",
        metavar="SETUP_PART",
        choices=[f"{s}_{p}" for s in SETUPS for p in PARTS],
        help="run --steps steps of one part (e.g. basic_loop) once, print nothing",
    )
    args = parser.parse_args()
    if args.only:
        name, part = args.only.split("_")
        PARTS[part](SETUPS[name], args.steps)
        return
    print(f"# numba: {'compiled' if jit.JIT else 'interpreted (SURPRISE_NO_JIT=1 or no numba)'}")
    print(f"# python {sys.version.split()[0]}, numpy {np.__version__}, {os.uname().machine}")
    print(f"jit: {int(jit.JIT)} 1")
    for name, setup in SETUPS.items():
        for part in PARTS:
            seconds = median_per_step(part, setup, args.steps, args.repeats)
            print(f"{name}_{part}: {seconds * 1e6:.1f} us")
            print(f"{name}_{part}_share_of_period: {seconds / PERIOD * 100:.2f} %")


if __name__ == "__main__":
    main()
