"""Speed of the engine: a whole paper-setting run (networks, safety, world, evolution), per
robot-step, against Enki's bare world in the same run.

One run: the ``paper`` setting's ``basic`` experiment (10 robots, 1000-step evaluations of 10 ms
steps) evolved for ``--evaluations`` evaluations with
:class:`master_service.experiments.engine_run.FastRun`'s loop (ask, evaluate on the engine, tell),
no files written. Many runs: ``--runs`` independent swarms (seeds 1..runs) in one process, each
evaluation round evaluating every run's candidate. Enki: its bare world (no networks, no evolution)
stepping 10 Thymio II in the same arena at the same 10 ms step, measured by ``benchmarks/sim.py``'s
Enki probe in the system python. CPU time of this process pinned to one core. Prints ``name: value
unit`` lines. Run: ``python benchmarks/engine.py [--evaluations 50] [--runs 4] [--repeats 3]
[--quick-start]``

``--quick-start`` also times the README's quick start end to end, ``surprise-master sim`` in a
child process on the same core (start-up, 1000 evaluations, the 10,000-step post-evaluation, the
run directory and report written): its robot-steps per CPU second of the child.

Targets: issue 11, a whole paper-setting run at least as fast per robot-step as Enki's bare
world; issue 25, the quick start at least 4 times Enki's bare world, a batch of runs at least 8
times.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from master_service.experiments.simulation_setup import (  # noqa: E402
    simulated_safety,
    simulation_experiment,
    world_config,
)
from minimize_surprise.evolution import OnePlusOne  # noqa: E402
from minimize_surprise.fitness import swarm_fitness  # noqa: E402
from minimize_surprise.network import GenomeLayout, spec_from_config  # noqa: E402
from simulator.engine import Swarm, evaluate_swarms  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sim import enki_python, measure_enki, pin_to_one_core  # noqa: E402


def run_many(runs: int, evaluations: int, *, batched: bool = False) -> float:
    """CPU seconds for ``evaluations`` evaluations of each of ``runs`` runs in this process: one
    after the other, or ``batched``, every round's candidates in one call (``evaluate_swarms``,
    as a study's batch)."""
    swarms, optimizers = [], []
    for seed in range(1, runs + 1):
        experiment = simulation_experiment("basic", setting="paper", seed=seed)
        spec = spec_from_config(experiment)
        swarms.append(Swarm(world_config(experiment), simulated_safety(experiment), spec, seed))
        optimizers.append(
            OnePlusOne(experiment.evolution, GenomeLayout(spec).size, experiment.seed)
        )
    steps = experiment.evaluation_steps
    swarms[0].evaluate(optimizers[0].ask().genome, 10)  # compiled before the clock starts
    cpu = time.process_time()
    for _ in range(evaluations):
        if batched:
            genomes = [opt.ask().genome for opt in optimizers]
            records = evaluate_swarms(swarms, genomes, steps)
        else:
            records = [
                swarm.evaluate(opt.ask().genome, steps)
                for swarm, opt in zip(swarms, optimizers, strict=True)
            ]
        for opt, record in zip(optimizers, records, strict=True):
            opt.tell(swarm_fitness([float(f) for f in record.fitness]))
    return time.process_time() - cpu


#: Robot-steps of the quick start with `surprise-master sim`'s defaults (paper setting, basic): 1000
#: evaluations of 1000 steps and the final stop, then the 10,000-step post-evaluation and its
#: stop, 10 robots.
QUICK_START_ROBOT_STEPS = 10 * (1000 * 1001 + 10_001)


def time_quick_start() -> float:
    """CPU seconds of ``surprise-master sim`` (the README's quick start) in a child process,
    compiled kernels cached by a first run that is not timed."""
    # This interpreter's own master (not whichever `surprise-master` is first on the PATH); its
    # errors are shown, its output is not.
    command = [
        sys.executable,
        "-c",
        "import sys; from master_service.cli import main; sys.exit(main())",
    ]
    quiet = {"check": True, "stdout": subprocess.DEVNULL}
    with tempfile.TemporaryDirectory() as tmp:
        # compiles what is not in the cache yet
        subprocess.run([*command, "sim", "--evaluations", "2", "--out", f"{tmp}/warm"], **quiet)
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        subprocess.run([*command, "sim", "--out", f"{tmp}/run"], **quiet)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    """Measure and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--evaluations", type=int, default=50)
    parser.add_argument("--runs", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--enki-python", default="/usr/bin/python3")
    parser.add_argument("--quick-start", action="store_true", help="time the quick start too")
    args = parser.parse_args()
    pin_to_one_core()
    per_step = 10 * 1000  # robot-steps per evaluation: 10 robots, 1000 steps
    one = [run_many(1, args.evaluations) for _ in range(args.repeats)]
    one_rate = per_step * args.evaluations / min(one)
    print(f"engine_one_run_robot_steps_per_s: {one_rate:.0f} robot-steps/s")
    print(
        "engine_one_run_robot_steps_per_s_median: "
        f"{per_step * args.evaluations / statistics.median(one):.0f} robot-steps/s"
    )
    print(f"engine_paper_basic_run_estimate: {10_100_000 / one_rate:.1f} s")
    rounds = args.evaluations // 2 or 1
    many = min(run_many(args.runs, rounds) for _ in range(args.repeats))
    many_rate = per_step * args.runs * rounds / many
    print(f"engine_{args.runs}_runs_robot_steps_per_s: {many_rate:.0f} robot-steps/s")
    batch = min(run_many(args.runs, rounds, batched=True) for _ in range(args.repeats))
    batch_rate = per_step * args.runs * rounds / batch
    print(f"engine_batch_of_{args.runs}_robot_steps_per_s: {batch_rate:.0f} robot-steps/s")
    quick_rate = None
    if args.quick_start:
        quick = time_quick_start()
        quick_rate = QUICK_START_ROBOT_STEPS / quick
        print(f"quick_start_cpu: {quick:.1f} s")
        print(f"quick_start_robot_steps_per_s: {quick_rate:.0f} robot-steps/s")
    python = enki_python(args.enki_python)
    if python is None:
        print("(Enki's python bindings not found: no Enki figures)", file=sys.stderr)
        return
    enki = measure_enki(python, 2000, 1, args.repeats, 0.01)
    enki_rate = enki["robots"] / enki["cpu_per_step"]
    print(f"enki_bare_world_robot_steps_per_s: {enki_rate:.0f} robot-steps/s")
    print(f"engine_run_vs_enki_bare_world: {one_rate / enki_rate:.2f} x")
    print(f"engine_batch_vs_enki_bare_world: {batch_rate / enki_rate:.2f} x")
    if quick_rate is not None:
        print(f"quick_start_vs_enki_bare_world: {quick_rate / enki_rate:.2f} x")


if __name__ == "__main__":
    main()
