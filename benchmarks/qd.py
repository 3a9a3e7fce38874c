"""Speed of MAP-Elites: seconds per robot-step of a QD batch against a batched (1+1)
evaluation, in the same run.

QD: :class:`master_service.experiments.qd_run.QDRun`'s whole step for ``--batches`` batches of
``--batch`` candidates (the scheduler's ask, every candidate's arena placed afresh, one
compiled call recording the trace, the measures and classes from it, the tell). (1+1): as a
study's batch evaluates its runs (``studies.batches``), ``--batch`` runs' candidates in one
compiled call (``evaluate_swarms``, nothing recorded), asked and told by their ``OnePlusOne``,
for as many robot-steps, and the study's own batch of :data:`studies.batches.BATCH_RUNS` runs.
The ``paper`` setting's ``basic`` experiment (10 robots, 1000-step evaluations of 10 ms), CPU
time of this process pinned to one core, the best of ``--repeats``. Prints ``name: value unit``
lines. Run: ``python benchmarks/qd.py [--batch 20] [--batches 5] [--repeats 3]``

Target (issue 37): a QD evaluation costs no more per robot-step than a batched (1+1) one
(``qd_over_batched_one_plus_one`` at most 1).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from master_service.experiments.engine_run import FastRun, run_batch  # noqa: E402
from master_service.experiments.qd_run import QDRun  # noqa: E402
from master_service.experiments.simulation_setup import simulation_experiment  # noqa: E402
from studies.batches import BATCH_RUNS  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from engine import run_many  # noqa: E402
from sim import pin_to_one_core  # noqa: E402

#: Robot-steps of one evaluation in the paper setting's basic arena: 10 robots, 1000 steps.
PER_EVALUATION = 10 * 1000


def time_qd(batch: int, batches: int) -> float:
    """CPU seconds of ``batches`` MAP-Elites steps of ``batch`` candidates (ask, evaluate with
    the trace, measures, tell), compiled kernels warmed before the clock starts."""
    experiment = simulation_experiment(
        "basic", setting="paper", seed=1, data={"setting": "paper", "optimizer": {"batch": batch}}
    )
    run = QDRun(experiment)
    scheduler = run._scheduler()
    run.evaluate(np.zeros((1, run.size)), 0)  # compiles the recording kernel
    cpu = time.process_time()
    for k in range(batches):
        genomes = scheduler.ask()
        fitness, behaviours = run.evaluate(genomes, k * batch)
        measures = [[b[m.name] for m in run.optimizer.measures] for b in behaviours]
        scheduler.tell(fitness, measures, **_fields(behaviours))
    return time.process_time() - cpu


def time_whole_runs(evaluations: int) -> tuple[float, float]:
    """CPU seconds per robot-step of a whole MAP-Elites run of ``4 * evaluations`` and of a
    batch of 4 whole (1+1) runs of ``evaluations`` each (see the module docstring)."""
    data = {"setting": "paper", "post_evaluation_steps": 1000, "optimizer": {"batch": 20}}
    with tempfile.TemporaryDirectory() as tmp:
        qd = simulation_experiment(
            "basic", setting="paper", seed=1, evaluations=4 * evaluations, data=data
        )
        run = QDRun(qd)
        cpu = time.process_time()
        result = run.run(f"{tmp}/qd", plots=False)
        qd_cpu = time.process_time() - cpu
        assert result is not None
        qd_steps = run.robot_steps + 10 * 1001 * len(result.summary.classes)
        runs = []
        for seed in range(1, 5):
            one = simulation_experiment(
                "basic", setting="paper", seed=seed, evaluations=evaluations, data=data
            )
            runs.append((FastRun(one), Path(tmp, f"{seed}")))
        cpu = time.process_time()
        run_batch(runs, plots=False)
        one_cpu = time.process_time() - cpu
    one_steps = 4 * (evaluations * PER_EVALUATION + 10 * 1001)
    return qd_cpu / qd_steps, one_cpu / one_steps


def _fields(behaviours: list[dict]) -> dict:
    # The archive's extra fields, as QDRun.run tells them.
    keep = ("rotation", "mean_cluster_size", "distance_covered", "backward_share")
    out = {name: [b[name] for b in behaviours] for name in keep}
    out["box_displacement"] = [b["box_displacement"] or 0.0 for b in behaviours]
    out["arena_seed"] = [b["arena_seed"] for b in behaviours]
    out["klass"] = [0 for _ in behaviours]
    return out


def main() -> None:
    """Measure and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=20)
    parser.add_argument("--batches", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--run-evaluations", type=int, default=200)
    args = parser.parse_args()
    pin_to_one_core()
    steps = PER_EVALUATION * args.batch * args.batches
    qd = min(time_qd(args.batch, args.batches) for _ in range(args.repeats)) / steps
    same = min(run_many(args.batch, args.batches, batched=True) for _ in range(args.repeats))
    same /= steps
    rounds = args.batch * args.batches // BATCH_RUNS
    study = min(run_many(BATCH_RUNS, rounds, batched=True) for _ in range(args.repeats))
    study /= PER_EVALUATION * BATCH_RUNS * rounds
    print(f"qd_batch_of_{args.batch}_s_per_robot_step: {qd:.3e} s")
    print(f"one_plus_one_batch_of_{args.batch}_s_per_robot_step: {same:.3e} s")
    print(f"one_plus_one_batch_of_{BATCH_RUNS}_s_per_robot_step: {study:.3e} s")
    print(f"qd_over_batched_one_plus_one: {qd / same:.3f} ratio")
    print(f"qd_over_study_batch_one_plus_one: {qd / study:.3f} ratio")
    whole = [time_whole_runs(args.run_evaluations) for _ in range(args.repeats)]
    qd_run, one_runs = min(w[0] for w in whole), min(w[1] for w in whole)
    print(f"qd_whole_run_s_per_robot_step: {qd_run:.3e} s")
    print(f"one_plus_one_batch_of_{BATCH_RUNS}_whole_runs_s_per_robot_step: {one_runs:.3e} s")
    print(f"qd_whole_run_over_batched_one_plus_one_runs: {qd_run / one_runs:.3f} ratio")


if __name__ == "__main__":
    main()
