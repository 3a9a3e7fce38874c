"""Speed of the simulated world: steps per second with random commands.

Each step includes computing every robot's sensor values, as the agents read them every step.
Commands are random and held for 10 steps (1 s at the default step of 0.1 s) so that robots
travel, meet and push boxes. Times are CPU time of this process pinned to one core
(``time.process_time``), so that a busy machine distorts them less; each figure is the best of
``--repeats`` runs (as ``timeit`` does), with the median of the runs printed too, and wall-clock
time for comparison.

For comparison, the same is measured for Enki (Debian's ``python3-enki2``, a 2D physics simulator
with the Thymio II model the lab setting's sensors follow) when the system python has its
bindings: 10 Thymio II robots in the basic arena (a 1 m carpet textured on the floor, walls 10 cm
beyond it, random non-overlapping start poses), random wheel speeds up to the world's top speed
held for 10 steps, every robot's 7 IR and 2 ground values read after each step (Enki computes them
inside its step). It runs in a subprocess of that python on the same core, timed there the same
way. Enki is a rigid-body simulator (friction, inertia, impulse collisions) with ray-cast IR
sensors, ours a kinematic one; Debian's Enki 1.6.99 also predates upstream's fix of its IR
initialisation (rays that stop meeting anything keep their last value), which changes the values
it reads but hardly what reading them costs.

Targets (issue 3): at least 50,000 robot-steps/s for ``basic`` (10 robots) and at most 1 ms per
step for ``gradient`` (4 robots, all 271 boxes); both at the default step.

Run: ``python benchmarks/sim.py [--steps N] [--seed S] [--dt SECONDS]`` (``--dt 0.01``: the
paper's Webots step, for every world here and Enki). Every figure is printed on its own line as
``name: value unit``.
"""

from __future__ import annotations

import os

# One core: keep numpy's thread pools (unused by these small arrays anyway) to one thread.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from simulator.scenarios import WorldConfig, scenario_config  # noqa: E402
from simulator.world import World  # noqa: E402


def pin_to_one_core() -> None:
    """Run on a single CPU where the platform allows it."""
    if hasattr(os, "sched_setaffinity"):
        cpus = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpus[-1]})


def measure(scenario: str, steps: int, seed: int, dt: float) -> dict[str, float]:
    """Step a fresh world of ``scenario``; return CPU and wall seconds per step and more."""
    world = World(scenario_config(scenario, {"dt": dt}), seed=seed)
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


def best_of(scenario: str, steps: int, seed: int, repeats: int, dt: float) -> dict[str, float]:
    """``measure`` ``repeats`` times; the fastest run, with the median CPU time added."""
    runs = [measure(scenario, steps, seed, dt) for _ in range(repeats)]
    return summarise(runs)


def summarise(runs: list[dict[str, float]]) -> dict[str, float]:
    """The fastest of ``runs`` (by CPU time), with the median CPU time added."""
    best = dict(min(runs, key=lambda r: r["cpu_per_step"]))
    best["median_cpu_per_step"] = float(np.median([r["cpu_per_step"] for r in runs]))
    return best


# Run by the system python (stdlib only: no numpy there); Enki's units are cm and cm/s. Prints a
# JSON list: each run's CPU and wall seconds per step.
ENKI_BENCHMARK = r"""
import json, math, os, random, sys, tempfile, time
import pyenki

a = json.loads(sys.argv[1])
side, carpet, robots, dt = a["side"], a["carpet"], a["robots"], a["dt"]
# The floor: the carpet grey 0.4 in the middle, white beyond it, 2 pixels per cm.
ppcm = 2
n = round(side * ppcm)
lo, hi = round((side - carpet) / 2 * ppcm), round((side + carpet) / 2 * ppcm)
grey, white = bytes([102, 102, 102]), bytes([255, 255, 255])
inside = white * lo + grey * (hi - lo) + white * (n - hi)
tmp = tempfile.mkdtemp()
floor = os.path.join(tmp, "floor.ppm")
with open(floor, "wb") as f:
    f.write(b"P6\n%d %d\n255\n" % (n, n))
    f.write(b"".join(inside if lo <= j < hi else white * n for j in range(n)))

def place(rng, thymios):
    # Wheel axes on the carpet, hulls (within 8 cm of the axis) wholly on it and apart by 2 cm.
    lim0, lim1, gap = (side - carpet) / 2 + 8.0, (side + carpet) / 2 - 8.0, 18.0
    placed = []
    while len(placed) < len(thymios):
        x, y = rng.uniform(lim0, lim1), rng.uniform(lim0, lim1)
        if all((x - u) ** 2 + (y - v) ** 2 >= gap * gap for u, v in placed):
            placed.append((x, y))
    for t, (x, y) in zip(thymios, placed):
        t.pos = (x, y)
        t.angle = rng.uniform(-math.pi, math.pi)
        t.leftSpeed = t.rightSpeed = t.angSpeed = 0.0
        t.speed = (0.0, 0.0)

def run(seed, steps):
    world = pyenki.WorldWithTexturedGround(float(side), float(side), floor)
    world.setRandomSeed(seed)
    thymios = [pyenki.Thymio2() for _ in range(robots)]
    for t in thymios:
        world.addObject(t)
    rng = random.Random(seed)
    v = a["max_speed"]
    commands = [[(rng.uniform(-v, v), rng.uniform(-v, v)) for _ in thymios]
                for _ in range(steps // 10 + 1)]
    place(random.Random(seed + 1), thymios)
    for _ in range(50):  # warm-up, as for ours
        for t, (l, r) in zip(thymios, commands[0]):
            t.leftSpeed, t.rightSpeed = l, r
        world.step(dt)
        for t in thymios:
            t.proximitySensorValues, t.groundSensorValues
    place(random.Random(seed + 1), thymios)  # the same start again
    cpu0, wall0 = time.process_time(), time.perf_counter()
    for k in range(steps):
        for t, (l, r) in zip(thymios, commands[k // 10]):
            t.leftSpeed, t.rightSpeed = l, r
        world.step(dt)
        for t in thymios:
            t.proximitySensorValues, t.groundSensorValues
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    return {"robots": robots, "cpu_per_step": cpu / steps, "wall_per_step": wall / steps}

runs = [run(a["seed"], a["steps"]) for _ in range(a["repeats"])]
os.remove(floor)
os.rmdir(tmp)
print(json.dumps(runs))
"""


def enki_python(python: str) -> str | None:
    """``python`` if it can import Enki's bindings (pyenki), else None."""
    try:
        found = subprocess.run([python, "-I", "-c", "import pyenki"], capture_output=True)
    except OSError:
        return None
    return python if found.returncode == 0 else None


def enki_runs(
    python: str, config: WorldConfig, steps: int, seed: int, repeats: int, dt: float
) -> list[dict[str, float]]:
    """Enki stepping ``config``'s robots on its carpet between its walls at steps of ``dt``
    in ``python`` (Enki's units are cm), ``repeats`` times: each run's CPU and wall seconds per
    step."""
    args = {
        "side": 2 * config.wall_half * 100,
        "carpet": config.arena_side * 100,
        "robots": config.robots,
        "max_speed": config.max_speed * 100,
        "dt": dt,
        "steps": steps,
        "seed": seed,
        "repeats": repeats,
    }
    done = subprocess.run(
        [python, "-I", "-c", ENKI_BENCHMARK, json.dumps(args)], capture_output=True, text=True
    )
    if done.returncode != 0:
        raise SystemExit(f"the Enki benchmark failed:\n{done.stderr}")
    return json.loads(done.stdout)


def measure_enki(python: str, steps: int, seed: int, repeats: int, dt: float) -> dict[str, float]:
    """Enki stepping the basic arena's robots (see the module docstring) in ``python``: its
    fastest run, with the median CPU time added."""
    return summarise(enki_runs(python, scenario_config("basic"), steps, seed, repeats, dt))


def main() -> None:
    """Measure both scenarios and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000, help="steps per run")
    parser.add_argument("--repeats", type=int, default=3, help="runs per scenario")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--dt", type=float, default=0.1, help="step length in seconds (the paper's Webots: 0.01)"
    )
    parser.add_argument(
        "--enki-python",
        default="/usr/bin/python3",
        help="a python with Enki's bindings (python3-enki2); Enki is skipped if it has none",
    )
    args = parser.parse_args()
    pin_to_one_core()
    print(f"step_length: {args.dt:g} s")

    basic = best_of("basic", args.steps, args.seed, args.repeats, args.dt)
    n = basic["robots"]
    print(f"basic_robot_steps_per_s: {n / basic['cpu_per_step']:.0f} robot-steps/s")
    print(f"basic_robot_steps_per_s_median: {n / basic['median_cpu_per_step']:.0f} robot-steps/s")
    print(f"basic_robot_steps_per_s_wall: {n / basic['wall_per_step']:.0f} robot-steps/s")
    print(f"basic_step_time: {basic['cpu_per_step'] * 1e6:.1f} us")

    python = enki_python(args.enki_python)
    if python is None:
        print(f"Enki skipped: {args.enki_python} cannot import pyenki", file=sys.stderr)
    else:
        enki = measure_enki(python, args.steps, args.seed, args.repeats, args.dt)
        m = enki["robots"]
        print(f"enki_basic_robot_steps_per_s: {m / enki['cpu_per_step']:.0f} robot-steps/s")
        print(
            f"enki_basic_robot_steps_per_s_median: "
            f"{m / enki['median_cpu_per_step']:.0f} robot-steps/s"
        )
        print(f"enki_basic_robot_steps_per_s_wall: {m / enki['wall_per_step']:.0f} robot-steps/s")
        print(f"enki_basic_step_time: {enki['cpu_per_step'] * 1e6:.1f} us")
        # Robot-steps per CPU second, ours over Enki's (both 10 robots).
        speedup = (n / basic["cpu_per_step"]) / (m / enki["cpu_per_step"])
        print(f"basic_speedup_vs_enki: {speedup:.1f} x")

    gradient = best_of("gradient", args.steps, args.seed, args.repeats, args.dt)
    print(f"gradient_step_time: {gradient['cpu_per_step'] * 1e3:.3f} ms")
    print(f"gradient_step_time_median: {gradient['median_cpu_per_step'] * 1e3:.3f} ms")
    print(f"gradient_step_time_wall: {gradient['wall_per_step'] * 1e3:.3f} ms")
    n = gradient["robots"]
    print(f"gradient_robot_steps_per_s: {n / gradient['cpu_per_step']:.0f} robot-steps/s")
    print(f"gradient_boxes_moved: {gradient['boxes_moved']} boxes")
    print(f"gradient_pushing_steps: {gradient['pushing_steps'] * 100:.1f} %")


if __name__ == "__main__":
    main()
